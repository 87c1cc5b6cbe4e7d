"""Von Mises–Fisher mean-shift with a 2-D proximity term, and frame clustering into instances.

Proximity variant (the paper's "also weighs 2D pixel proximity"): the kernel between a pixel
(embedding z, normalised position x) and a mode (μ, p) is the product

    K = exp(κ·(z·μ − 1)) · exp(−|x − p|² / (2σ²))

so modes move jointly in embedding space (renormalised weighted mean) and in the image plane
(weighted mean position). Positions are pixel coordinates divided by max(H, W). Two modes merge
only if their embeddings have cosine ≥ ``merge_threshold`` *and* they lie within ``merge_xy``
of each other, so identical-looking objects far apart stay separate. ``spatial_sigma = 0``
gives the plain vMF mean-shift (embedding only). The number of clusters is never given.

Devices: the mode finding (farthest-point seeds, mean-shift iterations, every pixel's nearest mode,
cluster ranking) is written once against numpy's array functions and runs on numpy arrays or on torch
tensors of any device (:func:`_namespace`), in float32 either way; :func:`cluster_frame` picks by the
type of its embeddings. numpy arrays give the project's reference results; a tensor on the CPU gives the
same labels on the test fixtures (float rounding differs, so a pixel equidistant between two modes may
differ). :func:`cluster_frames` runs the mode finding of several frames in one batch on the tensors'
device (frames padded to the largest, padding weighs zero); on CUDA, padded to ``max_pixels``, with the kernel as
one batched product of augmented vectors (:func:`_kernel_functions`) and replayed as one CUDA graph, since a frame's
mode finding is hundreds of small kernels. Merging the few dozen modes of a frame, the
connected-component split and small-part absorption run on the host (cv2/numpy): about 0.6 ms of a
320×240 frame and 1.5–2 ms of a 640×480 one on one CPU core (``bench/bench_inference.py``).
"""
from __future__ import annotations

import math
from dataclasses import astuple, dataclass
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from scipy import ndimage

from selfseg.method.cuda_graphs import GraphedFunction


@dataclass
class MeanShiftConfig:
    """Clustering settings; lengths in normalised image units (pixels / max(H, W))."""

    # vMF concentration: 1/τ of the contrastive loss (τ = 0.07), the sharpness the loss trains for.
    # Measured on a development set (benchmark preset, seed 100, never a test fold), supervised net:
    # κ 20 / merge .8 (the old defaults) IoU .656, κ 14 / merge .7 .726, κ 10 .723, κ 7 .703, κ 40 .548.
    kappa: float = 14.3
    n_seeds: int = 32  # initial modes, picked by farthest-point sampling in the kernel's metric
    iters: int = 10  # mean-shift iterations (stops early once modes move < 1e-4)
    merge_threshold: float = 0.7  # converged modes with cosine ≥ this (and close, see merge_xy) merge
    spatial_sigma: float = 0.15  # σ of the Gaussian proximity kernel; 0 disables the proximity term
    merge_xy: float = 0.3  # modes farther apart than this never merge (only when spatial_sigma > 0)
    max_pixels: int = 4000  # mode finding runs on at most this many pixels; all pixels are then assigned
    min_component_px: int = 50  # smaller connected components are absorbed by a neighbour or dropped
    connectivity: int = 8  # 4 or 8, for the connected-component split
    seed: int = 0  # for the pixel subsample

    def __post_init__(self):
        if self.kappa <= 0 or self.n_seeds < 1 or self.iters < 0 or self.max_pixels < 1:
            raise ValueError("kappa, n_seeds and max_pixels must be positive and iters ≥ 0")
        if self.spatial_sigma < 0:
            raise ValueError(f"spatial_sigma must be ≥ 0, got {self.spatial_sigma}")
        if self.connectivity not in (4, 8):
            raise ValueError(f"connectivity must be 4 or 8, got {self.connectivity}")


def _namespace(a):
    """The array functions for ``a``: numpy itself, or the same names and arguments on ``a``'s torch device."""
    if not isinstance(a, torch.Tensor):
        return np
    return SimpleNamespace(
        float32=torch.float32, inf=math.inf, linalg=torch.linalg, abs=torch.abs, amax=torch.amax,
        arange=lambda n: torch.arange(n, device=a.device), argmax=torch.argmax, bincount=torch.bincount,
        exp=torch.exp, minimum=torch.minimum,
        maximum=torch.clamp_min, ones_like=torch.ones_like, stack=torch.stack, where=torch.where,
        zeros_like=torch.zeros_like,
        asarray=lambda x, dtype=None: torch.as_tensor(x, dtype=dtype, device=a.device),
        zeros=lambda shape, dtype: torch.zeros(shape, dtype=dtype, device=a.device),
        argsort=lambda x, axis=-1, kind="stable": torch.argsort(x, dim=axis, stable=True))


def _asnumpy(a) -> np.ndarray:
    """``a`` as a numpy array on the host (numpy arrays and None pass through)."""
    return a.cpu().numpy() if isinstance(a, torch.Tensor) else a


def _log_kernel(z, x, mu, p, kappa: float, sigma: float, xp, xx=None):
    """log K between points (B×N×D, B×N×2) and modes (B×S×D, B×S×2) → B×N×S; ``xx``: the points' |x|²
    (B×N), if already computed."""
    out = kappa * (z @ mu.swapaxes(-1, -2) - 1.0)
    if sigma > 0:
        xx = (x * x).sum(-1) if xx is None else xx
        d2 = xx[..., :, None] + (p * p).sum(-1)[..., None, :] - 2.0 * x @ p.swapaxes(-1, -2)
        out -= xp.maximum(d2, 0.0) / (2.0 * sigma * sigma)
    return out


def _kernel_functions(z, x, kappa: float, sigma: float, xp, fused: bool = False):
    """(log_k, distance_to) over B frames of points (z B×N×D, x B×N×2 or None): ``log_k(mu, p)`` → B×N×S against
    modes (B×S×D, B×S×2 or None) as :func:`_log_kernel`, ``distance_to(i)`` → B×N, −log K from every point to
    each frame's point i (B indices).

    ``fused`` (torch tensors only): −log K = c_j + c_s − a_j·b_s with a = [κz, x/σ²], b = [z, x] and
    c = κ/2 + |x|²/(2σ²), one batched product per evaluation instead of a dozen small kernels (what the CUDA
    graph replays). The same quantity, rounded differently (and |x − p|² is not clamped at 0), so labels may
    differ from the numpy path's where two modes are equally near.
    """
    rows = xp.arange(len(z))
    if not fused:
        xx = None if x is None or sigma <= 0 else (x * x).sum(-1)
        return (lambda mu, p: _log_kernel(z, x, mu, p, kappa, sigma, xp, xx),
                lambda i: -_log_kernel(z, x, z[rows, i][:, None], None if x is None else x[rows, i][:, None], kappa,
                                       sigma, xp, xx)[..., 0])
    use_x = x is not None and sigma > 0
    s2 = sigma * sigma

    def augment(pts, pos):  # (a or b rows, c) of points or modes
        c = torch.full(pts.shape[:-1], kappa / 2, dtype=pts.dtype, device=pts.device)
        if not use_x:
            return pts, c
        return torch.cat([pts, pos], -1), c + (pos * pos).sum(-1) / (2 * s2)

    b, c = augment(z, x)
    a = torch.cat([kappa * z, x / s2], -1) if use_x else kappa * z

    def log_k(mu, p):
        bm, cm = augment(mu, p)
        return torch.baddbmm(-(c[..., :, None] + cm[..., None, :]), a, bm.swapaxes(-1, -2))

    def distance_to(i):
        return torch.baddbmm((c + c[rows, i][:, None])[..., None], a, b[rows, i][..., None], alpha=-1.0)[..., 0]

    return log_k, distance_to


def _farthest_points(distance_to, valid, n: int, xp):
    """Up to ``n`` farthest-point seeds per frame under ``distance_to`` (:func:`_kernel_functions`), starting from each
    frame's point 0.

    valid: B×N bool (False: padding). Returns (indices B×S, taken B×S bool): a frame takes no more seeds once every
    remaining point coincides with a seed, or all its points are seeds. Both conditions persist (distances only
    shrink), so a frame's taken seeds come first; the loop runs on without reading its results back (no device
    synchronisation).
    """
    count = valid.sum(-1)
    rows = xp.arange(len(valid))
    seeds, gaps = [xp.zeros_like(count)], []  # gaps: each later seed's distance to the seeds before it
    dist = xp.where(valid, distance_to(seeds[0]), -xp.inf)
    for _ in range(1, min(n, valid.shape[-1])):
        i = xp.argmax(dist, axis=-1)
        seeds.append(i)
        gaps.append(dist[rows, i])
        dist = xp.minimum(dist, distance_to(i))
    seeds = xp.stack(seeds, axis=-1)
    later = xp.stack(gaps, axis=-1) > 0 if gaps else seeds[:, :0] > 0
    taken = xp.arange(seeds.shape[-1]) < count[:, None]
    taken[:, 1:] &= later
    return seeds, taken


def _shift_modes(z, x, pad, seeds, taken, log_k, cfg: MeanShiftConfig, xp, early_stop: bool = True):
    """Mean-shift of every seed (B×S indices) over its frame's points → (modes B×S×D, positions B×S×2 or None).

    ``log_k`` as from :func:`_kernel_functions`, ``pad`` as in :func:`_weights`. A frame's modes stop moving once its
    taken seeds move less than 1e-4 in one iteration (embedding or position); with ``early_stop`` the loop ends when
    every frame has stopped (a host synchronisation per iteration), else it runs all ``cfg.iters`` iterations, which
    gives the same modes."""
    rows = xp.arange(len(z))[:, None]
    mu = z[rows, seeds]
    p = None if x is None else x[rows, seeds]
    moving = xp.ones_like(taken[:, 0])
    for _ in range(cfg.iters):
        w = _weights(log_k(mu, p), pad, xp)  # B×N×S
        m = w.swapaxes(-1, -2) @ z
        new_mu = m / xp.maximum(xp.linalg.norm(m, axis=-1, keepdims=True), 1e-12)
        shift = xp.amax(xp.abs(new_mu - mu), axis=-1)
        mu = xp.where(moving[:, None, None], new_mu, mu)
        if p is not None:
            new_p = (w.swapaxes(-1, -2) @ x) / xp.maximum(w.sum(-2), 1e-30)[..., None]
            shift = xp.maximum(shift, xp.amax(xp.abs(new_p - p), axis=-1))
            p = xp.where(moving[:, None, None], new_p, p)
        moving = moving & (xp.amax(xp.where(taken, shift, 0.0), axis=-1) >= 1e-4)
        if early_stop and not moving.any():
            break
    return mu, p


def _weights(log_k, pad, xp):
    """K = exp(log K) (B×N×S), zero at padded points (``pad``: B×N×1 bool, False at padding; None: none)."""
    w = xp.exp(log_k)
    return w if pad is None else w * pad


def _find_modes(z, x, valid, pad, cfg: MeanShiftConfig, xp, static: bool = False):
    """Seeds, mean-shift and each mode's kernel density for B frames of points (z B×N×D, x B×N×2 or None, valid
    B×N bool, ``pad`` as in :func:`_weights`) → (modes B×S×D, positions B×S×2 or None, density B×S, taken B×S).
    ``static``: no early stop and the fused kernel (:func:`_kernel_functions`): nothing synchronises with the host
    and a few hundred kernels in all, what a CUDA graph captures."""
    log_k, distance_to = _kernel_functions(z, x if cfg.spatial_sigma > 0 else None, cfg.kappa,
                                           float(cfg.spatial_sigma), xp, fused=static)
    seeds, taken = _farthest_points(distance_to, valid, cfg.n_seeds, xp)
    mu, p = _shift_modes(z, x, pad, seeds, taken, log_k, cfg, xp, early_stop=not static)
    return mu, p, _weights(log_k(mu, p), pad, xp).sum(-2), taken


_MODE_GRAPHS: dict[tuple, GraphedFunction] = {}


def _graphed_find_modes(cfg: MeanShiftConfig) -> GraphedFunction:
    """:func:`_find_modes` of torch tensors for ``cfg``, static, as a CUDA graph per batch size."""
    key = astuple(cfg)
    if key not in _MODE_GRAPHS:
        _MODE_GRAPHS[key] = GraphedFunction(
            lambda z, x, valid, pad: _find_modes(z, x, valid, pad, cfg, _namespace(z), static=True))
    return _MODE_GRAPHS[key]


def _merge_modes(mu: np.ndarray, p: np.ndarray | None, density: np.ndarray, cfg: MeanShiftConfig) -> np.ndarray:
    """Cluster id of each converged mode (S×D, S×2 or None, kernel density S): modes merge greedily, densest first."""
    group = np.full(len(mu), -1)
    kept: list[int] = []
    for s in np.argsort(-density, kind="stable"):
        for k in kept:
            close = float(mu[s] @ mu[k]) >= cfg.merge_threshold
            if close and p is not None:
                close = float(np.linalg.norm(p[s] - p[k])) <= cfg.merge_xy
            if close:
                group[s] = group[k]
                break
        else:
            group[s] = len(kept)
            kept.append(s)
    return group


def _to_host(mu, p, density, taken) -> tuple:
    """The modes (B×S×D, B×S×2 or None, B×S, B×S bool) as numpy arrays; tensors in one device-to-host copy."""
    if not isinstance(mu, torch.Tensor):
        return mu, p, density, taken
    d = mu.shape[-1]
    packed = torch.cat([mu, density[..., None], taken[..., None].to(mu.dtype)] + ([] if p is None else [p]),
                       -1).cpu().numpy()
    return (np.ascontiguousarray(packed[..., :d]), None if p is None else np.ascontiguousarray(packed[..., d + 2:]),
            np.ascontiguousarray(packed[..., d]), packed[..., d + 1] > 0.5)


def _stack_padded(arrays: list, xp, width: int = 0):
    """B arrays of N_i rows → B×max(N_i, width)×… with zero rows after each array's (B = 1 and no padding:
    a view)."""
    n = max(width, max(len(a) for a in arrays))
    if len(arrays) == 1 and len(arrays[0]) == n:
        return arrays[0][None]
    out = xp.zeros((len(arrays), n) + tuple(arrays[0].shape[1:]), dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
    return out


def _filled(lengths: list[int], width: int = 0) -> np.ndarray:
    """B×max(lengths, width) bool: True on the first ``lengths[i]`` entries of row i (what :func:`_stack_padded`
    fills)."""
    return np.arange(max(width, max(lengths))) < np.asarray(lengths)[:, None]


@torch.no_grad()
def _meanshift_frames(zs: list, xs: list | None, cfg: MeanShiftConfig, xp, static: bool | None = None) -> list:
    """Cluster several frames' points at once: ``zs`` N_i×D unit embeddings (float32, N_i ≥ 1), ``xs`` N_i×2
    positions (None when ``cfg.spatial_sigma`` = 0), all numpy arrays or all tensors on one torch device.

    Returns each frame's int64 labels in [0, k_i), ordered by cluster size (0 = largest), as the inputs' kind.
    Mode finding runs on at most ``cfg.max_pixels`` points per frame; every point is then assigned. ``static``
    (default: on CUDA): mode finding on frames padded to ``cfg.max_pixels`` points, so its shapes depend on the
    number of frames alone, as one CUDA graph (:mod:`~selfseg.method.cuda_graphs`; :func:`_find_modes`).
    """
    if static is None:
        static = xp is not np and zs[0].device.type == "cuda"
    subs = [np.sort(np.random.default_rng(cfg.seed).choice(len(z), cfg.max_pixels, replace=False))
            if len(z) > cfg.max_pixels else np.arange(len(z)) for z in zs]
    lengths = [len(s) for s in subs]
    width = cfg.max_pixels if static else 0
    valid = xp.asarray(_filled(lengths, width))
    pad = None if min(lengths) == valid.shape[-1] else valid[..., None]
    z = _stack_padded([zf[xp.asarray(s)] for zf, s in zip(zs, subs)], xp, width)
    x = None if xs is None else _stack_padded([xf[xp.asarray(s)] for xf, s in zip(xs, subs)], xp, width)
    if static:
        mu, p, density, taken = _graphed_find_modes(cfg)(z, x, valid, pad)
    else:
        mu, p, density, taken = _find_modes(z, x, valid, pad, cfg, xp)

    # Merging (a few dozen modes per frame) runs on the host.
    mu_h, p_h, density_h, taken_h = _to_host(mu, p, density, taken)
    groups = np.zeros(taken_h.shape, np.int64)
    for f, t in enumerate(taken_h):
        groups[f, t] = _merge_modes(mu_h[f][t], None if p_h is None else p_h[f][t], density_h[f][t], cfg)

    # Every point goes to its nearest converged mode, then to that mode's merged cluster.
    log_k = _log_kernel(_stack_padded(zs, xp), None if xs is None else _stack_padded(xs, xp), mu, p, cfg.kappa,
                        float(cfg.spatial_sigma), xp)
    if not taken_h.all():
        log_k = xp.where(xp.asarray(taken_h)[:, None, :], log_k, -xp.inf)
    b, s = groups.shape
    labels = xp.asarray(groups.ravel())[xp.argmax(log_k, axis=-1) + xp.asarray(np.arange(b)[:, None] * s)]  # B×M
    # Clusters ranked by size per frame; frame f's cluster c is f·k + c below.
    n_points, k = [len(z) for z in zs], int(groups.max()) + 1
    flat = labels + xp.asarray(np.arange(b)[:, None] * k)
    sizes = xp.bincount(flat[xp.asarray(_filled(n_points))], minlength=b * k).reshape(b, k)
    rank = xp.argsort(xp.argsort(-sizes, axis=-1, kind="stable"), axis=-1, kind="stable")
    labels = rank.reshape(-1)[flat]
    return [labels[f, :n] for f, n in enumerate(n_points)]


def vmf_meanshift(emb, xy, cfg: MeanShiftConfig):
    """Cluster unit embeddings (N×D) with optional positions (N×2, normalised) → labels N int64 in [0, k).

    ``emb``: a numpy array, or a torch tensor (clustered on its device, labels returned there). ``xy`` is
    required when ``cfg.spatial_sigma > 0`` and ignored otherwise. Labels are ordered by cluster size (0 = largest).
    """
    xp = _namespace(emb)
    z = xp.asarray(emb, dtype=xp.float32)
    n = len(z)
    if n == 0:
        return xp.asarray(np.zeros(0, np.int64))
    if cfg.spatial_sigma <= 0:
        return _meanshift_frames([z], None, cfg, xp)[0]
    if xy is None or tuple(np.shape(xy)) != (n, 2):
        raise ValueError(f"spatial_sigma > 0 needs xy of shape ({n}, 2), got {None if xy is None else np.shape(xy)}")
    return _meanshift_frames([z], [xp.asarray(xy, dtype=xp.float32)], cfg, xp)[0]


def split_components(labels: np.ndarray, connectivity: int = 8) -> np.ndarray:
    """Split every label (≥ 1; 0 = background) into its connected components → int32 map, ids 1..n (labels in
    increasing order, each label's components in raster order of their first pixel)."""
    out = np.zeros(labels.shape, np.int32)
    nxt = 1
    for c, box in enumerate(ndimage.find_objects(labels), start=1):  # labels < 1 are skipped
        if box is None:
            continue
        # Each label's bounding box, started at even coordinates: OpenCV's 8-connected labelling works on 2×2
        # blocks, so aligned crops number the components as the whole frame does.
        box = tuple(slice(b.start - b.start % 2, b.stop) for b in box)
        n, comp = cv2.connectedComponents((labels[box] == c).astype(np.uint8), connectivity=connectivity)
        sel = comp > 0
        out[box][sel] = comp[sel] + (nxt - 1)
        nxt += n - 1
    return out


def _border_counts(inst: np.ndarray, n: int) -> dict[int, dict[int, int]]:
    """{a: {b: number of 4-neighbour pixel pairs between components a and b}} of an id map (ids ≥ 1, 0 ignored)."""
    a, b = [], []
    for diff, step in ((inst[:, :-1] != inst[:, 1:], (0, 1)), (inst[:-1] != inst[1:], (1, 0))):
        ys, xs = np.nonzero(diff)
        a.append(inst[ys, xs])
        b.append(inst[ys + step[0], xs + step[1]])
    a, b = np.concatenate(a).astype(np.int64), np.concatenate(b).astype(np.int64)
    sel = (a > 0) & (b > 0)
    a, b = np.concatenate([a[sel], b[sel]]), np.concatenate([b[sel], a[sel]])
    keys, counts = np.unique(a * (n + 1) + b, return_counts=True)
    border: dict[int, dict[int, int]] = {}
    for key, cnt in zip(keys.tolist(), counts.tolist()):
        border.setdefault(key // (n + 1), {})[key % (n + 1)] = cnt
    return border


def absorb_small(inst: np.ndarray, min_px: int) -> np.ndarray:
    """Merge components smaller than ``min_px`` into the neighbour sharing the longest border
    (4-neighbourhood); small components without any neighbour become 0. Ids are compacted to 1..n."""
    inst = np.asarray(inst)
    if inst.dtype.kind not in "iu":
        inst = inst.astype(np.int64)
    n = int(inst.max(initial=0))
    if n == 0 or min_px <= 1:
        return inst.astype(np.int32)
    size = np.bincount(inst.ravel(), minlength=n + 1)
    small = (size > 0) & (size < min_px)
    small[0] = False
    if not small.any() and size[1:].all():  # nothing to absorb and ids already 1..n
        return inst.astype(np.int32)
    border = _border_counts(inst, n)

    parent = np.arange(n + 1)

    def find(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for c in np.argsort(size[1:], kind="stable") + 1:
        if size[c] >= min_px or size[c] == 0 or find(c) != c:
            continue
        votes: dict[int, int] = {}
        for nb, cnt in border.get(int(c), {}).items():
            r = find(nb)
            if r != c:
                votes[r] = votes.get(r, 0) + cnt
        if votes:
            target = max(votes, key=lambda r: (votes[r], size[r], -r))
            parent[c] = target
            size[target] += size[c]
        else:
            parent[c] = 0  # isolated and small: dropped
    roots = np.array([find(i) for i in range(n + 1)])
    _, compact = np.unique(roots, return_inverse=True)  # roots[0] = 0 stays 0
    return compact.astype(np.int32)[inst]


def _cluster(embs: list, fg_masks: list, cfg: MeanShiftConfig, static: bool | None = None) -> list[np.ndarray]:
    """Instance maps of frames whose D×H×W embeddings are all numpy arrays or all tensors on one torch device
    (``static`` as in :func:`_meanshift_frames`)."""
    xp = _namespace(embs[0] if embs else None)
    out, pixels, zs, xs = [], [], [], []
    for emb, fg in zip(embs, fg_masks):
        emb = xp.asarray(emb, dtype=xp.float32)
        fg = np.asarray(fg, dtype=bool)
        if emb.ndim != 3 or tuple(emb.shape[1:]) != fg.shape:
            raise ValueError(f"emb must be D×H×W matching fg_mask H×W, got {tuple(emb.shape)} and {fg.shape}")
        out.append(np.zeros(fg.shape, np.int32))
        vs, us = np.nonzero(fg)
        if len(vs):
            pixels.append((out[-1], vs, us))
            zs.append(emb[:, xp.asarray(vs), xp.asarray(us)].T)
            xs.append(xp.asarray(np.stack([us, vs], 1).astype(np.float32) / float(max(fg.shape))))
    if zs:
        labels = _meanshift_frames(zs, xs if cfg.spatial_sigma > 0 else None, cfg, xp, static)
        for (o, vs, us), lab in zip(pixels, labels):
            o[vs, us] = _asnumpy(lab) + 1
    return [absorb_small(split_components(o, cfg.connectivity), cfg.min_component_px) for o in out]


def cluster_frame(emb, fg_mask: np.ndarray, cfg: MeanShiftConfig) -> np.ndarray:
    """Instance map from per-pixel embeddings.

    emb: D×H×W float (unit norm per pixel), a numpy array or a torch tensor (mode finding then runs on its
    device); fg_mask: H×W bool. Returns int32 H×W, 0 = background, 1..n = instances: mean-shift over the
    foreground pixels, each cluster split into its connected components, components below ``min_component_px``
    absorbed or dropped.
    """
    return _cluster([emb], [fg_mask], cfg)[0]


def cluster_frames(embs, fg_masks: list[np.ndarray], cfg: MeanShiftConfig) -> list[np.ndarray]:
    """:func:`cluster_frame` of B frames: ``embs`` B×D×H×W. A torch tensor's frames go through mode finding
    together, in one batch on its device; numpy frames are clustered one by one."""
    if isinstance(embs, torch.Tensor):
        return _cluster(list(embs), list(fg_masks), cfg)
    return [cluster_frame(e, m, cfg) for e, m in zip(embs, fg_masks)]
