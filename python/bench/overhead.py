"""Python overhead against the CLI, and Ray against one process.

    python python/bench/overhead.py [--cli target/release/recon] [--runs 3] [--frames 6]

1. The README sample (`data/sample/000001-color.png` + `-label.png`): wall time of
   `recon infer` (a process: start, model load, reconstruction, files) against the same
   work from Python in a fresh interpreter (`import recon_rgbd`, `Engine()`,
   `reconstruct_files`), both with the CLI's defaults. The overhead is the difference of
   the medians over the CLI's median.
2. A `recon synth` dataset of `--frames` frames: one process (one Engine, all cores, the
   frames in turn) against `recon_rgbd.ray.reconstruct_dataset` with 2 local workers of one
   thread each: frames per second, peak memory per worker (ru_maxrss of the actor), and
   the fixed start-up cost (ray.init plus a one-frame run minus that frame's own time).

Compare figures only from one build profile on one machine; the script prints which
binary it used.
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RGB = REPO / "data/sample/000001-color.png"
MASKS = REPO / "data/sample/000001-label.png"


def timed(cmd, **kw):
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=REPO, **kw)
    return time.perf_counter() - t0


PY_ONE = """
import sys, recon
e = recon_rgbd.Engine()
e.reconstruct_files(sys.argv[1], sys.argv[2], sys.argv[3])
"""


def overhead(cli, runs, tmp):
    c, p = [], []
    for i in range(runs):
        c.append(timed([str(cli), "infer", "--rgbd", str(RGB), "--masks", str(MASKS), "--out", str(tmp / f"cli{i}")]))
        p.append(timed([sys.executable, "-c", PY_ONE, str(RGB), str(MASKS), str(tmp / f"py{i}")]))
    mc, mp = statistics.median(c), statistics.median(p)
    print(f"README sample, {runs} runs each (wall seconds): CLI {[round(x, 2) for x in c]}, Python {[round(x, 2) for x in p]}")
    print(f"  median CLI {mc:.2f} s, Python {mp:.2f} s: overhead {mp - mc:+.2f} s = {100 * (mp - mc) / mc:+.1f} % of the CLI's wall time")
    # In one interpreter, the binding's own cost per call: reconstruct_files wall time minus
    # the engine's reported seconds (preprocessing + every object's stage total).
    import recon_rgbd

    e = recon_rgbd.Engine()
    extra = []
    for i in range(runs):
        t0 = time.perf_counter()
        s = e.reconstruct_files(RGB, MASKS, tmp / f"warm{i}")
        wall = time.perf_counter() - t0
        inside = s["preprocess_s"] + sum(o["stage_seconds"]["total"] for o in s["objects"])
        extra.append((wall, wall - inside))
    w, x = statistics.median(a for a, _ in extra), statistics.median(b for _, b in extra)
    print(f"  warm engine: reconstruct_files {w:.2f} s, of which {x:.2f} s outside the engine's stage timers (mask/frame reading, file writing, binding)")


def ray_vs_one(frames, tmp):
    import recon_rgbd
    import recon_rgbd.ray as rr

    ds = tmp / "ds"
    recon_rgbd.synth(ds, scenes=frames, views=1, seed=11, width=320, height=240)
    fl = recon_rgbd.dataset_frames(ds)
    t0 = time.perf_counter()
    e = recon_rgbd.Engine()
    for f in fl:
        e.reconstruct_files(f["rgb"], f["masks"], tmp / "one" / f["frame"])
    one = time.perf_counter() - t0
    peak_one = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{len(fl)} frames (320×240, recon synth seed 11), one process, {os.cpu_count()} threads: {one:.1f} s, {len(fl) / one:.3f} frames/s, peak RSS {peak_one:.0f} MB")

    import ray
    import pyarrow.parquet as pq

    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    s1 = rr.reconstruct_dataset(fl[:1], tmp / "warmup", num_workers=1)
    t_one = time.perf_counter() - t0
    fs = pq.read_table(Path(s1["results"])).column("frame_seconds").to_pylist()[0]
    print(f"  Ray fixed start-up: ray.init {t_init:.1f} s; one-frame run {t_one:.1f} s of which {t_one - fs:.1f} s outside the frame (actor start, Engine load, scheduling)")
    t0 = time.perf_counter()
    s = rr.reconstruct_dataset(ds, tmp / "ray", num_workers=2, threads_per_worker=1)
    two = time.perf_counter() - t0
    t = pq.read_table(Path(s["results"])).to_pylist()
    peaks = {}
    for r in t:
        if r["worker_pid"] is not None:
            peaks[r["worker_pid"]] = max(peaks.get(r["worker_pid"], 0), r["worker_peak_rss_mb"])
    print(f"  Ray, 2 workers × 1 thread: {two:.1f} s, {len(fl) / two:.3f} frames/s ({one / two:.2f}× one process); failed {s['failed']}")
    print(f"  peak RSS per worker (MB): {', '.join(f'{v:.0f}' for v in peaks.values())}")
    ray.shutdown()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cli", default=str(REPO / "target/release/recon"))
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--skip-ray", action="store_true")
    a = ap.parse_args()
    import recon_rgbd

    print(f"recon {recon_rgbd.__version__} from {Path(recon_rgbd.__file__).parent}; CLI {a.cli}")
    with tempfile.TemporaryDirectory() as d:
        overhead(Path(a.cli), a.runs, Path(d))
        if not a.skip_ray:
            ray_vs_one(a.frames, Path(d))
    print(json.dumps({"cpu_count": os.cpu_count()}))


if __name__ == "__main__":
    main()
