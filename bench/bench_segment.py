"""``segment`` speed at 320×240 on the CPU: a saved model segmenting a folder of frames, end to end.

    .venv/bin/python bench/bench_segment.py [--data data/tiny] [--work /tmp/bench_segment]
                                            [--frames 20] [--threads 1] [--out bench/results/segment.json]

Trains a model with ``train`` (``ours-v2``, the methods' default "fast" network at the default
training scale of 320 px, a 10-step φ schedule: speed does not depend on training length),
upsamples ``--frames`` frames of the dataset's first video to 320×240 (K scaled), and runs
``segment`` in folder mode three ways: with foreground masks given (the depth points above the
support plane, precomputed), with ``--foreground plane`` (RANSAC per frame included) and with
every pixel as foreground. Reports frames/s as ``segment`` prints it (PNG reading and writing
included) and the process CPU seconds per frame; the machine's load average is recorded, since
the cores may be shared. Paper figure: about 6 fps.
"""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from common import bench_parser, write_result

from selfseg.dataset import Dataset
from selfseg.importers import scale_K
from selfseg.method.background import BackgroundConfig, frame_foreground
from selfseg.method.cli import segment_main
from selfseg.method.deploy import train_model
from selfseg.writers import depth_to_png_units, write_inst, write_rgb

W, H = 320, 240


def make_inputs(data: Path, folder: Path, n: int) -> Path:
    """rgb/, depth/ (mm units), fg/ (plane foreground) of n frames upsampled to W×H; returns the K file."""
    ds = Dataset(data)
    v = ds.video(ds.video_ids[0])
    K = scale_K(v.K(), W / ds.width, H / ds.height)
    for sub in ("rgb", "depth", "fg"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    for f in v.frame_ids[:n]:
        depth = cv2.resize(v.depth_m(f), (W, H), interpolation=cv2.INTER_NEAREST)
        write_rgb(folder / "rgb" / f"{f:06d}.png", cv2.resize(v.rgb(f), (W, H), interpolation=cv2.INTER_LINEAR))
        cv2.imwrite(str(folder / "depth" / f"{f:06d}.png"), depth_to_png_units(depth, 1.0))
        write_inst(folder / "fg" / f"{f:06d}.png", frame_foreground(depth, K, BackgroundConfig()).astype(np.uint16))
    k_path = folder / "K.txt"
    k_path.write_text(" ".join(repr(float(x)) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
    return k_path


def timed_segment(args: list[str], n: int) -> dict:
    t0, c0 = time.perf_counter(), time.process_time()
    assert segment_main(args + ["--quiet"]) == 0
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"fps": round(n / wall, 2), "ms_per_frame": round(1000 * wall / n, 1), "cpu_ms_per_frame": round(1000 * cpu / n, 1)}


def main() -> None:
    p = bench_parser(__doc__, "segment.json")
    p.add_argument("--data", type=Path, default=Path("data/tiny"), help="a generated tiny dataset (generate_scenes --preset tiny --out data/tiny)")
    p.add_argument("--work", type=Path, default=Path("/tmp/bench_segment"))
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--threads", type=int, default=1)  # two threads cost ~5x the CPU on the shared cores
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    model = a.work / "model"
    if not (model / "model.json").is_file():
        train_model("ours-v2", a.data, model, overrides=["phi1_train.steps=10", "phi1_train.batch_size=4",
                                                         f"stage_dir={a.work / 'stages'}"])
    inputs = a.work / "inputs"
    shutil.rmtree(inputs, ignore_errors=True)
    k_path = make_inputs(a.data, inputs, a.frames)
    n = len(list((inputs / "rgb").iterdir()))
    base = ["--model", str(model), "--rgb", str(inputs / "rgb")]
    depth = ["--depth", str(inputs / "depth"), "--intrinsics", str(k_path)]
    segment_main(base + ["--foreground", str(inputs / "fg"), "--out", str(a.work / "warm"), "--quiet"])  # warm-up
    rows = {
        "mask given": timed_segment(base + ["--foreground", str(inputs / "fg"), "--out", str(a.work / "o1")], n),
        "--foreground plane": timed_segment(base + depth + ["--foreground", "plane", "--out", str(a.work / "o2")], n),
        "all pixels": timed_segment(base + ["--out", str(a.work / "o3")], n),
    }
    print(f"segment at {W}×{H}, {n} frames, {a.threads} threads, load average {os.getloadavg()[0]:.1f}")
    print(f"{'foreground':20s} {'fps':>6s} {'ms/frame':>9s} {'CPU ms/frame':>13s}")
    for k, r in rows.items():
        print(f"{k:20s} {r['fps']:6.2f} {r['ms_per_frame']:9.1f} {r['cpu_ms_per_frame']:13.1f}")
    write_result(a.out, {"resolution": [W, H], "frames": n, "threads": a.threads, "method": "ours-v2",
                         "model": str(model), "results": rows})


if __name__ == "__main__":
    main()
