"""Inference speed (network + clustering, time split) and training throughput, on the CPU or a GPU.

    .venv/bin/python bench/bench_inference.py [--device cpu|cuda|auto] [--threads 2] [--repeats 5] [--batch 16]
        [--train-steps 3] [--parts inference,training] [--method-config YAML ...] [--before PATH]
        [--out bench/results/inference.json]

For each network preset and resolution it times the embedding network on a synthetic tabletop
frame (8 flat-coloured objects, ~35 % foreground) as the methods run it (resized to the training
scale ``TrainConfig.image_size``, embeddings resized back; native-size time also reported), alone and
in batches of ``--batch`` frames (seconds per frame), and the clustering at full resolution (vMF
mean-shift + components) on that frame's foreground with per-object embeddings plus noise, i.e. what
a trained network gives; an untrained network's embeddings would make clustering time meaningless.
The clustering is timed on numpy arrays (the CPU path, the project's reference results) and on
tensors on ``--device`` (the torch path, one frame and ``--batch`` frames of different objects in one
batch), with the host-side connected-component part on its own. ``fps`` is one frame end to end with
the clustering the methods use on that device (numpy on the CPU, torch on a GPU), the network and the clustering
timed apart and added; ``fps_numpy`` and ``fps_torch`` with each; ``fps_pipeline`` the two in one call as a method
runs them (host work of the clustering overlaps the network on a GPU). Reports the fastest wall and CPU time of
several runs, since the cores may be
shared (load average recorded). Training throughput is full training steps (batch, crop and
augmentation of the default TrainConfig) on the device, also as minutes per 800 steps, in float32 and with
the speed settings (channels_last; channels_last and bf16 autocast), one step of each in turn, each with its
speed-up over float32 (fastest and median step) and its first step's time; ``--variants`` adds bf16 with torch.compile
(``compile``: the network up to its stride-4 embeddings; ``compile_whole``), each with its first step's gradients
against the eager bf16 step's (``grad_cosine_vs_bf16``, ``grad_norm_ratio_vs_bf16``); on a GPU also float32 with the batches made ahead in threads, as
training makes them (``selfseg.method.train.training_batches``). On CUDA the network and the mode finding run as
CUDA graphs (``selfseg.method.cuda_graphs``); the single-frame figures without them are reported beside
(``*_eager``). ``--parts training`` times training alone. ``--method-config YAML`` (repeatable) times, instead of
the two presets, the network as that embedding-method config file runs it: its ``net``, its ``train`` settings
(scale, foreground crop, masked background, and the training variants on top of its own), ``test_flip`` and
``test_square_crop``; a foreground crop gives each frame its own input shape, so that network runs without CUDA
graphs, as the method does, unless the crops are square (one shape: a graph, frames batched). Paper figure: about
6 fps. ``--before``: an earlier run's JSON, kept under "before" for before/after comparisons.
"""
from __future__ import annotations

import os
import time
from dataclasses import fields, replace
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from common import bench_parser, write_result

from selfseg.config import load_config, to_dict
from selfseg.eval.provenance import cpu_model
from selfseg.fileio import read_json
from selfseg.method import cuda_graphs
from selfseg.method.embed_method import EmbeddingMethodConfig
from selfseg.method.features import embed_frames, foreground_box
from selfseg.method.meanshift import MeanShiftConfig, absorb_small, cluster_frame, cluster_frames, split_components
from selfseg.method.network import EmbeddingNet, NetConfig
from selfseg.method.train import (TrainConfig, new_embedding_net, prefetch_threads, resolve_device, step_loss,
                                  training_batches)

SIZES = ((320, 240), (640, 480))
# Training speed settings timed side by side (TrainConfig.channels_last, .precision). Each variant sets both fields,
# so a method config that trains in bf16 is still timed in float32 under "fp32".
TRAIN_VARIANTS = {"fp32": {"channels_last": False, "precision": "fp32"},
                  "channels_last": {"channels_last": True, "precision": "fp32"},
                  "bf16": {"channels_last": True, "precision": "bf16"},
                  "compile": {"channels_last": True, "precision": "bf16"},
                  "compile_whole": {"channels_last": True, "precision": "bf16"}}
# bf16 training with torch.compile (inductor), timed beside "bf16", whose gradients they are checked against: the
# network up to its stride-4 embeddings compiled, the float32 upsampling and normalisation eager ("compile"), or the
# whole network ("compile_whole": in torch 2.13 on the CPU every parameter's gradient comes out zero, a fault of
# inductor when the stride-4 network, the upsampling and the normalisation are one graph; aot_eager is right).
COMPILED = {"compile": "stride4", "compile_whole": "whole"}
DEFAULT_VARIANTS = ("fp32", "channels_last", "bf16")


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


def best_time(fn, repeats: int, device: torch.device) -> tuple[float, float]:
    """(fastest wall time, fastest process CPU time) of ``repeats`` calls after a warm-up, in seconds; on a GPU
    each call is timed to the end of its kernels.

    The CPU is shared: the minimum wall time is the closest to an unloaded machine's, and CPU time
    (all threads) is nearly independent of the load.
    """
    def call():
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    call()
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        call()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.min(wall)), float(np.min(cpu))


def bench_inference(net_cfg: NetConfig, cluster_cfg: MeanShiftConfig, train_cfg: TrainConfig, repeats: int,
                    batch: int, device: torch.device, flip: bool = False, square: bool = False) -> dict:
    """Per resolution: the method's pipeline (network at the training scale ``train_cfg.image_size``, on the
    foreground box (grown to a square with ``square``) and with the background masked where ``train_cfg`` says so,
    mirrored too with ``flip``;
    embeddings resized to the frame, clustering at full resolution), its parts, and the network at native size."""
    torch.manual_seed(0)
    net = EmbeddingNet(net_cfg).to(device).eval()
    image_size, margin = train_cfg.image_size, train_cfg.crop_margin
    out = {}
    for w, h in SIZES:
        frames = [synthetic_frame(w, h, seed=i) for i in range(batch)]
        rgb, inst = frames[0]
        embs = [object_embeddings(f[1], net_cfg.embed_dim, seed=i) for i, f in enumerate(frames)]
        masks = [f[1] > 0 for f in frames]
        emb, fg = embs[0], masks[0]
        emb_dev, embs_dev = torch.from_numpy(emb).to(device), torch.from_numpy(np.stack(embs)).to(device)

        def network(rgbs, fgs, size=image_size):  # the network as the method runs it on these frames
            boxes = None if margin is None else [foreground_box(m, margin) for m in fgs]
            return embed_frames(net, rgbs, device, size, boxes, fgs if train_cfg.mask_background else None, flip,
                                square and size > 0)

        t_net, c_net = best_time(lambda: network([rgb], [fg]), repeats, device)
        t_native, _ = best_time(lambda: network([rgb], [fg], 0), repeats, device)
        t_batch, _ = best_time(lambda: network([f[0] for f in frames], masks), repeats, device)
        t_numpy, c_numpy = best_time(lambda: cluster_frame(emb, fg, cluster_cfg), repeats, device)
        t_torch, _ = best_time(lambda: cluster_frame(emb_dev, fg, cluster_cfg), repeats, device)
        t_torch_batch, _ = best_time(lambda: cluster_frames(embs_dev, masks, cluster_cfg), repeats, device)
        t_components, _ = best_time(lambda: absorb_small(split_components(inst, cluster_cfg.connectivity),
                                                         cluster_cfg.min_component_px), repeats, device)
        if device.type == "cuda":  # the same without CUDA graphs: kernels launched one by one from Python
            cuda_graphs.ENABLED = False
            t_net_eager, _ = best_time(lambda: network([rgb], [fg]), repeats, device)
            t_torch_eager, _ = best_time(lambda: cluster_frame(emb_dev, fg, cluster_cfg), repeats, device)
            cuda_graphs.ENABLED = True
        pred, pred_torch = cluster_frame(emb, fg, cluster_cfg), cluster_frame(emb_dev, fg, cluster_cfg)
        t_cluster = t_numpy if device.type == "cpu" else t_torch
        # One call as a method runs a frame: the network, then the clustering of (here, the synthetic) embeddings on
        # the same device and stream, so what the host does while the device runs counts once.
        emb_used = emb if device.type == "cpu" else emb_dev
        t_pipeline, _ = best_time(lambda: (network([rgb], [fg]),
                                           cluster_frame(emb_used, fg, cluster_cfg)), repeats, device)
        row = {"network_s": t_net, "clustering_s": t_cluster, "total_s": t_net + t_cluster,
               "fps": 1 / (t_net + t_cluster),
               "network_cpu_s": c_net, "clustering_cpu_s": c_numpy, "network_native_resolution_s": t_native,
               "network_batched_s_per_frame": t_batch / batch, "clustering_numpy_s": t_numpy,
               "clustering_torch_s": t_torch, "clustering_torch_batched_s_per_frame": t_torch_batch / batch,
               "components_s": t_components, "clustering_share": t_cluster / (t_net + t_cluster),
               "fps_numpy": 1 / (t_net + t_numpy), "fps_torch": 1 / (t_net + t_torch),
               "pipeline_s": t_pipeline, "fps_pipeline": 1 / t_pipeline}
        if device.type == "cuda":
            row |= {"network_eager_s": t_net_eager, "clustering_torch_eager_s": t_torch_eager,
                    "fps_eager": 1 / (t_net_eager + t_torch_eager)}
        rounded = {k: round(v, 5 if k.endswith(("_s", "_frame")) else 3) for k, v in row.items()}
        out[f"{w}x{h}"] = rounded | {
            "fg_pixels": int(fg.sum()), "objects": int(inst.max()),
            "instances_found": int(len(np.unique(pred[pred > 0]))),
            "torch_labels_equal_numpy": bool(np.array_equal(pred, pred_torch))}
        print(f"  {w}x{h}: network {t_net * 1000:.1f} ms (at {image_size} px{', flipped too' if flip else ''}; "
              f"{t_native * 1000:.0f} ms at native size; "
              f"{t_batch / batch * 1000:.1f} ms/frame in batches of {batch}) + clustering numpy {t_numpy * 1000:.1f} / "
              f"torch {t_torch * 1000:.1f} ms (batched {t_torch_batch / batch * 1000:.1f} ms/frame; components "
              f"{t_components * 1000:.1f} ms) = {1 / (t_net + t_cluster):.2f} fps, {1 / t_pipeline:.2f} fps in one "
              f"call "
              f"({out[f'{w}x{h}']['instances_found']} instances of {inst.max()}); CPU time "
              f"{c_net * 1000:.0f} + {c_numpy * 1000:.0f} ms", flush=True)
        if device.type == "cuda":
            print(f"    without CUDA graphs: network {t_net_eager * 1000:.1f} ms + clustering "
                  f"{t_torch_eager * 1000:.1f} ms "
                  f"= {row['fps_eager']:.1f} fps", flush=True)
    return out


def bench_training(net_cfg: NetConfig, train_cfg: TrainConfig, steps: int, device: torch.device,
                   variants: tuple[str, ...] = DEFAULT_VARIANTS) -> dict:
    """Training steps under each of ``variants`` (of TRAIN_VARIANTS; "fp32" among them), interleaved (one step of each in turn, ``steps`` rounds after a
    warm-up round), so a change in the machine's load hits every variant alike: {variant: timings}, with the
    speed-up of each variant's fastest step over float32's. Each step makes its own batch here. Where training makes
    its batches ahead in threads (a GPU), float32 training as train_embedding runs it is timed after them
    ("fp32_batches_ahead": 3 × ``steps`` consecutive steps, the batches from :func:`training_batches`; its
    ``run_s_per_step`` is the whole run's wall time per step, the pool's start included)."""
    rgb, inst = synthetic_frame(640, 480)
    source = [(rgb, inst - 1)]
    runs, models, first_s, grads = {}, {}, {}, {}
    for variant in variants:
        cfg = replace(train_cfg, **TRAIN_VARIANTS[variant])
        torch.manual_seed(0)  # every variant starts from the same weights
        net = new_embedding_net(net_cfg, cfg, device)
        models[variant] = compiled(net, COMPILED.get(variant))
        runs[variant] = (cfg, net, torch.optim.AdamW(net.parameters(), lr=cfg.lr), [], [])

    def step(cfg, net, opt, i, batch=None, model=None, keep_grads=None):
        loss = step_loss(net if model is None else model, source, cfg, i, device, batch)
        opt.zero_grad()
        loss.backward()
        if keep_grads is not None:
            grads[keep_grads] = torch.cat([p.grad.detach().float().flatten() for p in net.parameters()
                                           if p.grad is not None])
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for i in range(steps + 1):
        for variant, (cfg, net, opt, wall, cpu) in runs.items():
            t, c = time.perf_counter(), time.process_time()
            step(cfg, net, opt, i, model=models[variant], keep_grads=variant if i == 0 else None)
            if i > 0:  # round 0 warms up (and compiles)
                wall.append(time.perf_counter() - t)
                cpu.append(time.process_time() - c)
            else:
                first_s[variant] = time.perf_counter() - t
    threads, extra = prefetch_threads(device), {}
    if threads:
        cfg, net, opt, wall, cpu = runs["fp32"][0], runs["fp32"][1], runs["fp32"][2], [], []
        t_run = time.perf_counter()
        for i, batch in zip(range(3 * steps), training_batches(source, cfg, range(3 * steps), threads)):
            t, c = time.perf_counter(), time.process_time()
            step(cfg, net, opt, i, batch)
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        runs["fp32_batches_ahead"] = (cfg, net, opt, wall, cpu)
        extra = {"batch_threads": threads, "run_s_per_step": round((time.perf_counter() - t_run) / (3 * steps), 3)}
    out = {}
    for variant, (cfg, _, _, wall, cpu) in runs.items():
        t = float(np.min(wall))
        out[variant] = {"batch_size": cfg.batch_size, "crop": list(cfg.crop), "channels_last": cfg.channels_last,
                        "precision": cfg.precision, "step_s": round(t, 3),
                        "step_median_s": round(float(np.median(wall)), 3), "step_cpu_s": round(float(np.min(cpu)), 3),
                        "images_per_s": round(cfg.batch_size / t, 2), "steps_per_s": round(1 / t, 3),
                        "minutes_per_800_steps": round(800 * t / 60, 2),
                        "minutes_per_800_median_steps": round(800 * float(np.median(wall)) / 60, 2)}
        if variant in first_s:
            out[variant]["first_step_s"] = round(first_s[variant], 2)
        if variant in COMPILED:
            out[variant] |= {"compiled": COMPILED[variant], **gradient_agreement(grads[variant], grads["bf16"])}
    if extra:
        out["fp32_batches_ahead"] |= extra | {
            "minutes_per_800_steps_whole_run": round(800 * extra["run_s_per_step"] / 60, 2)}
    for t in out.values():
        t["speedup_vs_fp32"] = round(out["fp32"]["step_s"] / t["step_s"], 2)
        t["median_speedup_vs_fp32"] = round(out["fp32"]["step_median_s"] / t["step_median_s"], 2)
    return out


def compiled(net: EmbeddingNet, part: str | None):
    """What a training step calls: ``net`` itself, its stride-4 part compiled with torch.compile ("stride4"; the
    float32 upsampling and normalisation of ``forward`` stay eager), or the whole network compiled ("whole")."""
    if part is None:
        return net
    if part == "whole":
        return torch.compile(net)
    net.forward_stride4 = torch.compile(net.forward_stride4)
    return net


def gradient_agreement(grad: torch.Tensor, reference: torch.Tensor) -> dict:
    """The first step's parameter gradients against the eager bf16 step's (same weights, same batch): cosine and
    norm ratio (1 and 1 when they agree; a gradient of zeros gives 0 and 0)."""
    norm = float(grad.norm() * reference.norm())
    return {"grad_cosine_vs_bf16": round(float(grad @ reference) / norm, 4) if norm > 0 else 0.0,
            "grad_norm_ratio_vs_bf16": round(float(grad.norm() / reference.norm()), 4)}


def method_networks(paths: list[str]) -> dict[str, tuple[NetConfig, TrainConfig, bool, bool]]:
    """{file name: (net, training settings, test-time flip, square crops)} of the φ2 network each method config file
    sets: its ``net``, ``train``, ``test_flip`` and ``test_square_crop`` over :class:`EmbeddingMethodConfig`'s
    defaults (every embedding method's; the file's other sections are the method's own, so no method class, and
    none of its imports, is needed)."""
    keys = {f.name for f in fields(EmbeddingMethodConfig)}
    out = {}
    for path in paths:
        data = yaml.safe_load(Path(path).read_text()) or {}
        try:
            cfg = load_config(EmbeddingMethodConfig, base={k: v for k, v in data.items() if k in keys})
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        out[Path(path).name] = (cfg.net, cfg.train, cfg.test_flip, cfg.test_square_crop)
    return out


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU model."""
    return torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model()


def main() -> None:
    ap = bench_parser(__doc__, "inference.json")
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu",
                    help="where the network, the torch clustering and training run (auto: cuda if available)")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads of torch and OpenCV")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=16, help="frames per batch for the batched network and clustering")
    ap.add_argument("--train-steps", type=int, default=3, help="timed training steps of each variant")
    ap.add_argument("--parts", default="inference,training", help="what to time: inference, training or both")
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS),
                    help=f"training variants to time, fp32 among them (of {', '.join(TRAIN_VARIANTS)}; bf16 is "
                         f"emulated and 10× slower on a CPU without AVX512-BF16 or AMX; the compiled ones need "
                         f"bf16 beside them and compile for a minute or so)")
    ap.add_argument("--method-config", action="append", default=[], metavar="YAML",
                    help="time the network as an embedding method's config file sets it, instead of the presets")
    ap.add_argument("--before", type=Path, help="an earlier run's JSON, kept under 'before'")
    args = ap.parse_args()
    try:
        nets = method_networks(args.method_config) if args.method_config else \
            {name: (NetConfig.preset(name), TrainConfig(), False, False) for name in ("default", "fast")}
    except (ValueError, OSError, yaml.YAMLError) as e:
        ap.error(f"--method-config: {e}")
    args.parts = set(args.parts.split(","))
    if not args.parts or not args.parts <= {"inference", "training"}:
        ap.error(f"--parts: inference, training or both, got {','.join(sorted(args.parts))}")
    args.variants = tuple(args.variants.split(","))
    if "fp32" not in args.variants or not set(args.variants) <= set(TRAIN_VARIANTS) or \
            (set(args.variants) & set(COMPILED) and "bf16" not in args.variants):
        ap.error(f"--variants: fp32 and any of {', '.join(TRAIN_VARIANTS)} (bf16 with a compiled one), "
                 f"got {','.join(args.variants)}")
    load_at_start = os.getloadavg()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    device = resolve_device(args.device)
    cluster_cfg = MeanShiftConfig()
    train_cfg = TrainConfig()
    results = {"device": str(device), "device_name": device_name(device), "threads": args.threads,
               "thread_env": {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS") if k in os.environ},
               "repeats": args.repeats, "batch": args.batch,
               "cluster_config": to_dict(cluster_cfg), "train_config": to_dict(train_cfg), "nets": {}}
    for name, (net_cfg, net_train_cfg, flip, square) in nets.items():
        print(f"net {name}: {to_dict(net_cfg)}", flush=True)
        entry = {"net_config": to_dict(net_cfg)}
        if args.method_config:
            entry |= {"train_config": to_dict(net_train_cfg), "test_flip": flip, "test_square_crop": square}
        if "inference" in args.parts:
            entry["inference"] = bench_inference(net_cfg, cluster_cfg, net_train_cfg, args.repeats, args.batch,
                                                 device, flip, square)
        if "training" in args.parts:
            entry["training"] = bench_training(net_cfg, net_train_cfg, args.train_steps, device, args.variants)
            for variant, t in entry["training"].items():
                print(f"  training ({variant}): {t['images_per_s']} images/s, {t['minutes_per_800_steps']} min per "
                      f"800 steps, ×{t['speedup_vs_fp32']} (median ×{t['median_speedup_vs_fp32']}; batch "
                      f"{net_train_cfg.batch_size}, crop {net_train_cfg.crop})", flush=True)
        results["nets"][name] = entry
    if args.before is not None:
        results["before"] = read_json(args.before)
    write_result(args.out, results, load_at_start)


if __name__ == "__main__":
    main()
