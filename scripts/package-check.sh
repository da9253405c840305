#!/usr/bin/env bash
# Packages every public crate of the workspace as `cargo publish` would and checks the
# packages: each under crates.io's 10 MiB upload limit, every file an include_bytes! /
# include_str! names present inside its package, the metadata crates.io shows set, and the
# packaged root crate free of tests, data and models. Prints each .crate's size.
#
#   scripts/package-check.sh           # quick: no compilation (about 10 s; CI runs this)
#   scripts/package-check.sh --verify  # also builds every package as cargo publish does,
#                                      # in its own target folder (all dependencies from
#                                      # scratch: tens of minutes on 2 cores)
#
# The packages go to $PACKAGE_CHECK_DIR (default target/package-check): never into the
# build's own target/debug, so the checkout's binaries are not replaced by the packaged
# ones (which carry no embedded recgen-nano; see crates/core/build.rs).
set -euo pipefail
cd "$(dirname "$0")/.."
verify=--no-verify
if [ "${1:-}" = "--verify" ]; then verify=; fi
out="${PACKAGE_CHECK_DIR:-$PWD/target/package-check}"
# Not published: the Python extension (a wheel) and the test helpers (a dev-dependency,
# dropped from the packages).
private=(recon-python recon-testkit)
excludes=()
for p in "${private[@]}"; do excludes+=(--exclude "$p"); done
log="$out/package.log"
mkdir -p "$out"
if ! CARGO_TARGET_DIR="$out" cargo package --workspace "${excludes[@]}" $verify --allow-dirty >"$log" 2>&1; then
  cat "$log"
  echo "package-check: cargo package failed" >&2
  exit 1
fi
fail=0
# cargo's own complaints (missing metadata, files left out that a target needs) fail the check.
# The root crate leaves its tests and example out on purpose (they read fixtures beside them).
if grep -E '^(warning|error)' "$log" | grep -vE '^warning: ignoring (test|example|bench) `[a-z0-9_]+` as `(tests|examples|benches)/[a-z0-9_]+.rs` is not included in the published package$'; then
  echo "package-check: cargo package warned (above)" >&2
  fail=1
fi
limit=$((10 * 1024 * 1024))
crates=$(ls "$out"/package/*.crate)
unpacked="$out/unpacked"
rm -rf "$unpacked"
mkdir -p "$unpacked"
printf '%-28s %12s\n' package bytes
for c in $crates; do
  size=$(stat -c %s "$c")
  name=$(basename "$c" .crate)
  printf '%-28s %12d\n' "$name" "$size"
  if [ "$size" -ge "$limit" ]; then
    echo "package-check: $name is over crates.io's 10 MiB limit" >&2
    fail=1
  fi
  tar -xzf "$c" -C "$unpacked"
  dir="$unpacked/$name"
  for key in description license rust-version documentation keywords categories; do
    if ! grep -q "^$key = " "$dir/Cargo.toml"; then
      echo "package-check: $name has no $key" >&2
      fail=1
    fi
  done
  # Every literal include path resolves inside the package (paths built with concat!/env!
  # are the build script's: the embedded model, absent from packages by design).
  while IFS=: read -r file _ path; do
    if [ ! -f "$(dirname "$file")/$path" ]; then
      echo "package-check: ${file#"$unpacked"/} includes $path, which the package lacks" >&2
      fail=1
    fi
  done < <(grep -rnoE --include='*.rs' 'include_(bytes|str)!\("[^"]+"\)' "$dir" | sed -E 's/:[0-9]+:include_(bytes|str)!\("/:x:/; s/"\)$//')
done
# The root crate is the library and the CLI only.
root=$(ls -d "$unpacked"/recon-[0-9]*)
for absent in tests data models benches docs python crates; do
  if [ -e "$root/$absent" ]; then
    echo "package-check: the recon package holds $absent/" >&2
    fail=1
  fi
done
for present in src/main.rs build.rs README.md; do
  if [ ! -f "$root/$present" ]; then
    echo "package-check: the recon package lacks $present" >&2
    fail=1
  fi
done
if [ "$fail" -ne 0 ]; then
  exit 1
fi
echo "package-check: $(echo "$crates" | wc -w) packages ok${verify:+ (not compiled: --verify builds them)}"
