"""Inference speed (network + clustering, time split) and training throughput on the CPU.

    .venv/bin/python bench/bench_inference.py [--threads 2] [--repeats 5] [--out bench/results/inference.json]

For each network preset and resolution it times the embedding network on a synthetic tabletop
frame (8 flat-coloured objects, ~35 % foreground) as the methods run it (resized to the training
scale ``TrainConfig.image_size``, embeddings resized back; native-size time also reported), and
the clustering at full resolution (vMF mean-shift + components) on that frame's foreground with
per-object embeddings plus noise, i.e. what a trained network gives; an untrained network's
embeddings would make clustering time meaningless. Reports the
fastest wall and CPU time of several runs, since the cores may be shared (load average recorded).
Training throughput is images/s of full training steps (batch, crop and augmentation of the
default TrainConfig). Paper figure: about 6 fps.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from selfseg.config import to_dict
from selfseg.fileio import write_json
from selfseg.method.features import embed_frames
from selfseg.method.meanshift import MeanShiftConfig, cluster_frame
from selfseg.method.network import EmbeddingNet, NetConfig
from selfseg.method.train import TrainConfig, step_loss

SIZES = ((320, 240), (640, 480))


def synthetic_frame(w: int, h: int, n_objects: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 H×W×3, instance map int H×W) of flat-coloured ellipses on a grey table."""
    rng = np.random.default_rng(seed)
    rgb = np.full((h, w, 3), 150, np.uint8)
    inst = np.zeros((h, w), np.int32)
    for k in range(1, n_objects + 1):
        c = (int(rng.uniform(0.15, 0.85) * w), int(rng.uniform(0.2, 0.8) * h))
        axes = (int(rng.uniform(0.05, 0.11) * w), int(rng.uniform(0.07, 0.15) * h))
        angle = float(rng.uniform(0, 180))
        cv2.ellipse(inst, c, axes, angle, 0, 360, k, -1)
        cv2.ellipse(rgb, c, axes, angle, 0, 360, tuple(int(v) for v in rng.integers(0, 255, 3)), -1)
    return rgb, inst


def object_embeddings(inst: np.ndarray, dim: int, noise: float = 0.15, seed: int = 0) -> np.ndarray:
    """D×H×W unit embeddings: one random direction per instance plus per-pixel noise."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(inst.max() + 1, dim))
    emb = centers[inst] + noise * rng.normal(size=inst.shape + (dim,))
    return (emb / np.linalg.norm(emb, axis=-1, keepdims=True)).astype(np.float32).transpose(2, 0, 1)


def best_time(fn, repeats: int) -> tuple[float, float]:
    """(fastest wall time, fastest process CPU time) of ``repeats`` calls after a warm-up, in seconds.

    The CPU is shared: the minimum wall time is the closest to an unloaded machine's, and CPU time
    (all threads) is nearly independent of the load.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.min(wall)), float(np.min(cpu))


def bench_inference(net_cfg: NetConfig, cluster_cfg: MeanShiftConfig, image_size: int, repeats: int) -> dict:
    """Per resolution: the method's pipeline (network at the training scale ``image_size``, embeddings
    resized to the frame, clustering at full resolution) and, for reference, the network at native size."""
    torch.manual_seed(0)
    net = EmbeddingNet(net_cfg).eval()
    out = {}
    for w, h in SIZES:
        rgb, inst = synthetic_frame(w, h)
        emb, fg = object_embeddings(inst, net_cfg.embed_dim), inst > 0
        (t_net, c_net) = best_time(lambda: embed_frames(net, [rgb], "cpu", image_size), repeats)
        (t_native, _) = best_time(lambda: embed_frames(net, [rgb], "cpu"), repeats)
        (t_cluster, c_cluster) = best_time(lambda: cluster_frame(emb, fg, cluster_cfg), repeats)
        pred = cluster_frame(emb, fg, cluster_cfg)
        out[f"{w}x{h}"] = {"network_s": round(t_net, 4), "clustering_s": round(t_cluster, 4),
                           "total_s": round(t_net + t_cluster, 4), "fps": round(1.0 / (t_net + t_cluster), 2),
                           "network_cpu_s": round(c_net, 4), "clustering_cpu_s": round(c_cluster, 4),
                           "network_native_resolution_s": round(t_native, 4), "fg_pixels": int(fg.sum()),
                           "objects": int(inst.max()), "instances_found": int(len(np.unique(pred[pred > 0])))}
        print(f"  {w}x{h}: network {t_net * 1000:.0f} ms (at {image_size} px; {t_native * 1000:.0f} ms at native size)"
              f" + clustering {t_cluster * 1000:.0f} ms = {1.0 / (t_net + t_cluster):.2f} fps "
              f"({out[f'{w}x{h}']['instances_found']} instances of {inst.max()}); CPU time "
              f"{c_net * 1000:.0f} + {c_cluster * 1000:.0f} ms", flush=True)
    return out


def bench_training(net_cfg: NetConfig, train_cfg: TrainConfig, steps: int) -> dict:
    rgb, inst = synthetic_frame(640, 480)
    source = [(rgb, inst - 1)]
    torch.manual_seed(0)
    net = EmbeddingNet(net_cfg)
    opt = torch.optim.AdamW(net.parameters(), lr=train_cfg.lr)

    def step(i: int = 0):
        loss = step_loss(net, source, train_cfg, i, torch.device("cpu"))
        opt.zero_grad()
        loss.backward()
        opt.step()

    t, c = best_time(step, steps)
    return {"batch_size": train_cfg.batch_size, "crop": list(train_cfg.crop), "step_s": round(t, 3),
            "step_cpu_s": round(c, 3), "images_per_s": round(train_cfg.batch_size / t, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--train-steps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "inference.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cluster_cfg = MeanShiftConfig()
    train_cfg = TrainConfig()
    results = {"threads": args.threads, "cpu": platform.processor() or platform.machine(),
               "load_average_at_start": list(os.getloadavg()), "torch": torch.__version__,
               "cluster_config": to_dict(cluster_cfg), "train_config": to_dict(train_cfg), "nets": {}}
    for name in ("default", "fast"):
        net_cfg = NetConfig.preset(name)
        print(f"net {name}: {to_dict(net_cfg)}", flush=True)
        entry = {"net_config": to_dict(net_cfg),
                 "inference": bench_inference(net_cfg, cluster_cfg, train_cfg.image_size, args.repeats)}
        entry["training"] = bench_training(net_cfg, train_cfg, args.train_steps)
        print(f"  training: {entry['training']['images_per_s']} images/s "
              f"(batch {train_cfg.batch_size}, crop {train_cfg.crop})", flush=True)
        results["nets"][name] = entry
    results["load_average_at_end"] = list(os.getloadavg())
    write_json(args.out, results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
