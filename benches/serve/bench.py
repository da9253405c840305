"""`recon serve` figures (issue 31 §6): HTTP overhead, throughput and latency, memory.

    RECON_CLI=target/release/recon python3 benches/serve/bench.py [--reps 3] [--frames 12]

Needs the Python package (`pip install ./python`) built from the same tree as the binary.

1. **Overhead.** The README sample (`data/sample/000001-color.png`, its depth, intrinsics
   and instance-id label) with the default model and default options: in-process
   `Engine.reconstruct` against the same arrays through `recon_rgbd.Client.reconstruct` to a
   `recon serve` on 127.0.0.1 (upload, queue, compute, answer, and the objects' files
   fetched and parsed). The server and the engine never compute at once. Overhead = (HTTP
   median − in-process median) / in-process median; `--reps` runs each.
2. **Throughput and latency.** A stream of `recon synth` frames (`--frames`, 160×120 by
   default) posted by `--clients` concurrent clients (each sends its share in turn, wait=true)
   to servers started with `--workers 1` and `--workers 2`: frames per second over the
   stream's wall time, p50 and p99 request latency. The model is `--stream-model`
   (`default`, or `tiny`: the random tiny architecture, plumbing only).
3. **Memory.** The server's peak resident memory (`/metrics`) at rest (model loaded, no
   job yet) and after the stream (its high-water mark under load).

The machine running it is what the figures describe: say which binary, profile and
machine, and whether other work shared it. The script prints all of it.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

import recon_rgbd

REPO = Path(__file__).resolve().parents[2]
SAMPLE_RGB = REPO / "data/sample/000001-color.png"
SAMPLE_LABEL = REPO / "data/sample/000001-label.png"


def cli_path():
    env = os.environ.get("RECON_CLI")
    if env:
        return Path(env)
    for p in (REPO / "target/release/recon", REPO / "target/debug/recon"):
        if p.is_file():
            return p
    sys.exit("no recon binary: set RECON_CLI")


class Server:
    """`recon serve --bind 127.0.0.1:0` with `args`, from the repository."""

    def __init__(self, cli, data, args):
        self.log = open(Path(data).with_suffix(".log"), "wb")
        self.p = subprocess.Popen(
            [str(cli), "serve", "--bind", "127.0.0.1:0", "--data-dir", str(data), *args],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=self.log,
        )
        line = self.p.stdout.readline().decode()
        if not line.startswith("recon serve: listening on http://"):
            raise SystemExit(f"recon serve did not start: {line!r}")
        self.url = "http://" + line.strip().rsplit("http://", 1)[1]

    def metric(self, name):
        text = urllib.request.urlopen(self.url + "/metrics", timeout=30).read().decode()
        for line in text.splitlines():
            if line.startswith(name + " "):
                return float(line.split()[1])
        return None

    def stop(self):
        self.p.terminate()
        self.p.wait(timeout=120)
        self.log.close()


def percentile(v, p):
    v = sorted(v)
    return v[round((len(v) - 1) * p)]


def overhead(cli, reps, tmp):
    fr = recon_rgbd.load_frame(SAMPLE_RGB)
    ids = recon_rgbd.load_masks(SAMPLE_LABEL)
    label = np.zeros(fr["rgb"].shape[:2], np.uint16)
    for o in ids["objects"]:
        label[o["mask"]] = o["id"]
    engine = recon_rgbd.Engine()
    server = Server(cli, tmp / "overhead", [])
    client = recon_rgbd.Client(server.url)
    local, remote = [], []
    try:
        for _ in range(reps):
            t0 = time.perf_counter()
            a = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], label)
            local.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            b = client.reconstruct(fr["rgb"], fr["depth"], fr["K"], label)
            remote.append(time.perf_counter() - t0)
            assert [o.label for o in a] == [o.label for o in b] and all(np.array_equal(x.pose, y.pose) for x, y in zip(a, b))
        peak = server.metric("recon_peak_resident_memory_bytes")
    finally:
        server.stop()
    ml, mr = statistics.median(local), statistics.median(remote)
    return {
        "objects": len(a),
        "in_process_s": local,
        "http_s": remote,
        "median_in_process_s": ml,
        "median_http_s": mr,
        "overhead_pct": 100 * (mr - ml) / ml,
        "server_peak_rss_mib": peak / 2**20 if peak else None,
    }


def stream(cli, workers, frames, clients, model, tmp):
    args = ["--workers", str(workers), "--queue", str(max(clients, 1) * 2)]
    if model == "tiny":
        args += ["--weights", "random", "--config", str(REPO / "models/recgen-tiny.json"), "--steps", "2"]
    server = Server(cli, tmp / f"stream-w{workers}", args)
    client = recon_rgbd.Client(server.url)
    rest = server.metric("recon_peak_resident_memory_bytes")
    lat, errors = [], []
    lock = threading.Lock()

    def run(mine):
        for fr, ids in mine:
            t0 = time.perf_counter()
            try:
                client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids)
            except recon_rgbd.ReconError as e:
                with lock:
                    errors.append(str(e))
                continue
            with lock:
                lat.append(time.perf_counter() - t0)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=run, args=(frames[i::clients],)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    loaded = server.metric("recon_peak_resident_memory_bytes")
    server.stop()
    return {
        "workers": workers,
        "frames": len(frames),
        "clients": clients,
        "ok": len(lat),
        "errors": errors[:3],
        "wall_s": wall,
        "frames_per_s": len(lat) / wall,
        "p50_s": percentile(lat, 0.5) if lat else None,
        "p99_s": percentile(lat, 0.99) if lat else None,
        "peak_rss_at_rest_mib": rest / 2**20 if rest else None,
        "peak_rss_under_load_mib": loaded / 2**20 if loaded else None,
    }


def synth_frames(n, width, height, tmp):
    root = tmp / "synth"
    recon_rgbd.synth(root, scenes=n, views=1, seed=11, width=width, height=height)
    out = []
    for f in recon_rgbd.dataset_frames(root)[:n]:
        fr = recon_rgbd.load_frame(f["rgb"])
        ids = np.zeros(fr["rgb"].shape[:2], np.uint16)
        for i, m in enumerate(recon_rgbd.load_masks(f["masks"])["objects"]):
            ids[m["mask"]] = i + 1
        out.append((fr, ids))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3, help="runs of the README sample each way")
    ap.add_argument("--frames", type=int, default=12, help="synth frames in the stream")
    ap.add_argument("--clients", type=int, default=4, help="concurrent clients of the stream")
    ap.add_argument("--size", default="160x120", help="synth frame size WxH")
    ap.add_argument("--stream-model", choices=["default", "tiny"], default="default")
    ap.add_argument("--skip-overhead", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    a = ap.parse_args()
    cli = cli_path()
    w, h = map(int, a.size.split("x"))
    print(f"binary {cli} ({subprocess.run([str(cli), '--version'], capture_output=True, text=True).stdout.strip()}), python {platform.python_version()}, {os.cpu_count()} CPUs, {platform.node()}")
    print(f"load average before: {os.getloadavg()}")
    figures = {"binary": str(cli), "cpus": os.cpu_count(), "loadavg_before": os.getloadavg()}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if not a.skip_overhead:
            o = overhead(cli, a.reps, tmp)
            figures["overhead"] = o
            print(f"\nREADME sample, default model, {o['objects']} objects, {a.reps} runs each (wall s):")
            print(f"  in-process Engine.reconstruct {[round(x, 2) for x in o['in_process_s']]}, median {o['median_in_process_s']:.2f}")
            print(f"  HTTP Client.reconstruct       {[round(x, 2) for x in o['http_s']]}, median {o['median_http_s']:.2f}")
            print(f"  overhead {o['overhead_pct']:+.1f} %  (server peak RSS {o['server_peak_rss_mib']:.0f} MiB)")
        frames = synth_frames(a.frames, w, h, tmp)
        figures["stream"] = []
        print(f"\nstream: {len(frames)} synth frames {w}×{h}, {a.clients} clients, model {a.stream_model}")
        print(f"  {'workers':>7} {'ok':>4} {'wall s':>8} {'frames/s':>9} {'p50 s':>7} {'p99 s':>7} {'RSS rest MiB':>13} {'RSS load MiB':>13}")
        for workers in (1, 2):
            s = stream(cli, workers, frames, a.clients, a.stream_model, tmp)
            figures["stream"].append(s)
            print(
                f"  {workers:>7} {s['ok']:>4} {s['wall_s']:>8.1f} {s['frames_per_s']:>9.3f} {s['p50_s'] or 0:>7.2f} {s['p99_s'] or 0:>7.2f}"
                f" {s['peak_rss_at_rest_mib'] or 0:>13.0f} {s['peak_rss_under_load_mib'] or 0:>13.0f}"
            )
            if s["errors"]:
                print(f"    errors: {s['errors']}")
    figures["loadavg_after"] = os.getloadavg()
    print(f"\nload average after: {os.getloadavg()}")
    if a.json:
        a.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
