#!/usr/bin/env bash
# One sitting: recon and upstream PyTorch side by side on this machine, for docs/performance.md.
#
#   bash benches/upstream/sitting.sh --trellis /path/to/TRELLIS --python /path/to/venv/bin/python \
#       --out /tmp/sitting [--isas native,avx2] [--threads 2] [--skip-e2e]
#
# Runs, per instruction set (`native`: what the CPU has; `avx2`: recon capped with RECON_ISA=avx2
# and upstream with ATEN_CPU_CAPABILITY=avx2, MKL_ENABLE_INSTRUCTIONS=AVX2, ONEDNN_MAX_CPU_ISA=AVX2,
# which stands in for an AVX2-only machine):
#   1. recon's kernel bench (GEMM/attention against the measured peak);
#   2. upstream's SS flow and SS decoder (harness.py), as shipped and with glibc keeping freed memory
#      (a row still running after 10 min is stopped and noted: on the AVX2 cap, oneDNN's bf16 conv3d
#      has no fast kernel and ran single-threaded for over 12 min);
#   3. recon's same modules, paired with upstream's report (--compare);
#   4. recon's stage-2 step on the realistic voxel set;
#   5. a whole object at paper settings (25 + 25 steps, the architecture file's CFG) in bf16, what
#      `--dtype auto` picks for recgen-large;
# then the modules at 1 thread (speed-up per thread) and the README sample with the default model.
# Every report is JSON under --out; the console log is --out/sitting.log. Nothing else should run.
set -euo pipefail
cd "$(dirname "$0")/../.."
TRELLIS="" PY="python3" OUT="" ISAS="native,avx2" THREADS=2 E2E=1
while [ $# -gt 0 ]; do
  case "$1" in
    --trellis) TRELLIS="$2"; shift 2 ;;
    --python) PY="$2"; shift 2 ;;
    --out) OUT="$2"; shift 2 ;;
    --isas) ISAS="$2"; shift 2 ;;
    --threads) THREADS="$2"; shift 2 ;;
    --skip-e2e) E2E=0; shift ;;
    *) echo "sitting.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
[ -n "$TRELLIS" ] && [ -n "$OUT" ] || { echo "sitting.sh: --trellis and --out are required" >&2; exit 2; }
RECON="$PWD/target/release/recon"
[ -x "$RECON" ] || { echo "sitting.sh: build first: cargo build --release" >&2; exit 2; }
mkdir -p "$OUT"
exec > >(tee -a "$OUT/sitting.log") 2>&1
stamp() { echo "== $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg) :: $*"; }
stamp "start: $("$RECON" --version | head -1); $(git rev-parse --short HEAD)$(git diff --quiet || echo +dirty)"
grep -m1 "model name" /proc/cpuinfo
grep -o -w -E 'avx2|fma|avx512f|avx512_bf16|amx_bf16|amx_tile' /proc/cpuinfo | sort -u | tr '\n' ' '; echo
"$PY" -c "import torch; print('torch', torch.__version__, 'capability', torch.backends.cpu.get_cpu_capability())"
KEEP=(MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824)
for isa in ${ISAS//,/ }; do
  case "$isa" in
    native) RENV=() UENV=() ;;
    avx2) RENV=(RECON_ISA=avx2) UENV=(ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2) ;;
    *) echo "sitting.sh: --isas takes native and avx2" >&2; exit 2 ;;
  esac
  stamp "$isa: kernels"
  env "${RENV[@]}" "$RECON" bench --sections kernels --quick --threads "$THREADS" --json "$OUT/kernels-$isa.json"
  stamp "$isa: upstream as shipped"
  env "${UENV[@]}" "$PY" benches/upstream/harness.py --trellis "$TRELLIS" --threads "$THREADS" --row-timeout 600 --json "$OUT/upstream-$isa.json"
  stamp "$isa: upstream, glibc keeping freed memory"
  env "${UENV[@]}" "${KEEP[@]}" "$PY" benches/upstream/harness.py --trellis "$TRELLIS" --threads "$THREADS" --row-timeout 600 --json "$OUT/upstream-keep-$isa.json"
  stamp "$isa: recon modules"
  env "${RENV[@]}" "$RECON" bench --sections modules --modules ss_flow,ss_decoder --dtype f32,bf16 --threads "$THREADS" \
    --compare "$OUT/upstream-$isa.json" --json "$OUT/modules-$isa.json"
  stamp "$isa: recon stage 2"
  env "${RENV[@]}" "$RECON" bench --sections stage2 --dtype f32,bf16 --threads "$THREADS" --json "$OUT/stage2-$isa.json"
done
stamp "recon modules at 1 thread (native)"
"$RECON" bench --sections modules --modules ss_flow,ss_decoder --dtype f32,bf16 --threads 1 --json "$OUT/modules-native-1thread.json"
stamp "README sample, default model, three runs"
for i in 1 2 3; do
  /usr/bin/time -f "sample run $i: %e s wall, %M KiB peak" "$RECON" infer --rgbd data/sample/000001-color.png \
    --masks data/sample/000001-label.png --out "$OUT/sample$i" >/dev/null
done
if [ "$E2E" = 1 ]; then
  for isa in ${ISAS//,/ }; do
    case "$isa" in native) RENV=() ;; avx2) RENV=(RECON_ISA=avx2) ;; esac
    stamp "$isa: whole object at paper settings"
    env "${RENV[@]}" "$RECON" bench --sections e2e --dtype bf16 --threads "$THREADS" --json "$OUT/e2e-$isa.json"
  done
fi
stamp "done"
