"""Von Mises–Fisher mean-shift with a 2-D proximity term, and frame clustering into instances.

Proximity variant (the paper's "also weighs 2D pixel proximity"): the kernel between a pixel
(embedding z, normalised position x) and a mode (μ, p) is the product

    K = exp(κ·(z·μ − 1)) · exp(−|x − p|² / (2σ²))

so modes move jointly in embedding space (renormalised weighted mean) and in the image plane
(weighted mean position). Positions are pixel coordinates divided by max(H, W). Two modes merge
only if their embeddings have cosine ≥ ``merge_threshold`` *and* they lie within ``merge_xy``
of each other, so identical-looking objects far apart stay separate. ``spatial_sigma = 0``
gives the plain vMF mean-shift (embedding only). The number of clusters is never given.

Devices: the mode finding (farthest-point seeds, mean-shift iterations) and every pixel's nearest mode are written
once against numpy's array functions and run on numpy arrays or on torch tensors of any device (:func:`_namespace`),
in float32 either way; :func:`cluster_frame` picks by the type of its embeddings. numpy arrays give the project's
reference results; a tensor on the CPU gives the same labels on the test fixtures (float rounding differs, so a pixel
equidistant between two modes may differ). :func:`cluster_frames` runs the mode finding of several frames in one
batch on the tensors' device (frames padded to the largest, padding weighs zero); on CUDA, padded to ``max_pixels``,
with the kernel and the moments as batched products of augmented rows (:func:`_kernel_functions`) and replayed as one
CUDA graph, since a frame's mode finding is hundreds of small kernels. One device-to-host copy then brings back the
modes and every pixel's nearest mode; merging the few dozen modes of a frame, ranking clusters, the
connected-component split and small-part absorption run on the host (numpy/cv2), and the host's work that needs no
device result (foreground pixels, the subsample) comes before the first transfer, beside the network's forward pass.
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
        concatenate=torch.cat, exp=torch.exp, minimum=torch.minimum,
        maximum=torch.clamp_min, ones_like=torch.ones_like, stack=torch.stack, where=torch.where,
        zeros_like=torch.zeros_like,
        asarray=lambda x, dtype=None: torch.as_tensor(x, dtype=dtype, device=a.device),
        zeros=lambda shape, dtype: torch.zeros(shape, dtype=dtype, device=a.device),
        argsort=lambda x, axis=-1, kind="stable": torch.argsort(x, dim=axis, stable=True))


def _asnumpy(a) -> np.ndarray:
    """``a`` as a numpy array on the host (numpy arrays and None pass through)."""
    return a.cpu().numpy() if isinstance(a, torch.Tensor) else a


def _max_argmax(a, xp):
    """(largest value, its first index) along the last axis, in one pass on tensors."""
    if xp is np:
        i = np.argmax(a, axis=-1)
        return a[np.arange(len(a)), i], i
    return torch.max(a, -1)


def _log_kernel(z, x, mu, p, kappa: float, sigma: float, xp, xx=None):
    """log K between points (B×N×D, B×N×2) and modes (B×S×D, B×S×2) → B×N×S; ``xx``: the points' |x|²
    (B×N), if already computed."""
    out = kappa * (z @ mu.swapaxes(-1, -2) - 1.0)
    if sigma > 0:
        xx = (x * x).sum(-1) if xx is None else xx
        d2 = xx[..., :, None] + (p * p).sum(-1)[..., None, :] - 2.0 * x @ p.swapaxes(-1, -2)
        out -= xp.maximum(d2, 0.0) / (2.0 * sigma * sigma)
    return out


# Kernel value of padding in the fused kernel: log K = −_FAR (exp: 0). Finite, so no 0·∞ anywhere in a product.
_FAR = 1e30


def _kernel_functions(z, x, pad, kappa: float, sigma: float, xp, fused: bool = False) -> SimpleNamespace:
    """The kernel over B frames of points (z B×N×D unit embeddings, x B×N×2 positions or None when ``sigma`` = 0,
    ``pad`` B×N bool, False at padding, or None). A mode is one row [μ, p] (D + 2; [μ] without positions), so
    modes are B×S×(D + 2) arrays. Returns a namespace of

    - ``points``: the points as modes, B×N×(D + 2);
    - ``log_k(m)``: log K → B×N×S against modes m as :func:`_log_kernel`, −∞ (or −1e30) at padding;
    - ``distance_to(i)``: −log K → B×N from every point to each frame's point i (B indices);
    - ``moments(w)``: (Σ w z, Σ w x or None, Σ w) → B×S×D, B×S×2, B×S of weights w (B×N×S) over the points.

    ``fused`` (torch tensors only): log K = κz·μ + x·p/σ² − κ − (|x|² + |p|²)/(2σ²), written as one product of
    augmented rows (below), so each kernel evaluation and the moments are one batched product, a few kernels per step
    where the plain form needs a dozen (what the CUDA graph replays); padding gets log K = −1e30. The same
    quantities, rounded differently (and |x − p|² is not clamped at 0), so labels may differ from the numpy path's
    where two modes are equally near.
    """
    d = z.shape[-1]
    rows = xp.arange(len(z))
    use_x = x is not None and sigma > 0
    x = x if use_x else None
    if not fused:
        xx = None if x is None else (x * x).sum(-1)

        def log_k(m):
            out = _log_kernel(z, x, m[..., :d], None if x is None else m[..., d:], kappa, sigma, xp, xx)
            return out if pad is None else xp.where(pad[..., None], out, -xp.inf)

        def distance_to(i):
            return -_log_kernel(z, x, z[rows, i][:, None], None if x is None else x[rows, i][:, None], kappa, sigma,
                                xp, xx)[..., 0]

        def moments(w):
            wt = w.swapaxes(-1, -2)
            return wt @ z, None if x is None else wt @ x, w.sum(-2)

        return SimpleNamespace(points=z if x is None else xp.concatenate([z, x], -1), log_k=log_k,
                               distance_to=distance_to, moments=moments)

    s2 = sigma * sigma
    # log K = a·[μ, p, 1, |p|²] with a = [κz, x/σ², −c, −1/(2σ²)], c = κ + |x|²/(2σ²) (1e30 at padding); without
    # positions a = [κz, −κ] against [μ, 1]. Points augmented as modes: [z, x, 1, |x|²].
    c = torch.full_like(z[..., :1], kappa)  # B×N×1
    one = torch.ones_like(c)
    if x is None:
        a, aug = [kappa * z], [z, one]
    else:
        xx = (x * x).sum(-1, keepdim=True)
        c = c + xx / (2 * s2)
        a, aug = [kappa * z, x / s2], [z, x, one, xx]
    if pad is not None:
        c = torch.where(pad[..., None], c, _FAR)
    a = torch.cat(a + [-c] + ([] if x is None else [one / (-2 * s2)]), -1)
    a_neg, points_aug = -a, torch.cat(aug, -1)

    def log_k(m):
        one_m = torch.ones_like(m[..., :1])
        cols = [m, one_m] if x is None else [m, one_m, (m[..., d:] * m[..., d:]).sum(-1, keepdim=True)]
        return a @ torch.cat(cols, -1).swapaxes(-1, -2)

    def distance_to(i):
        return (a_neg @ points_aug[rows, i][..., None])[..., 0]

    def moments(w):  # Σ w·[z, x, 1, |x|²]
        mom = w.swapaxes(-1, -2) @ points_aug
        return mom[..., :d], None if x is None else mom[..., d:d + 2], mom[..., d if x is None else d + 2]

    return SimpleNamespace(points=points_aug[..., :d + (0 if x is None else 2)], log_k=log_k, distance_to=distance_to,
                           moments=moments)


def _farthest_points(distance_to, valid, n: int, xp):
    """Up to ``n`` farthest-point seeds per frame under ``distance_to`` (:func:`_kernel_functions`), starting from each
    frame's point 0.

    valid: B×N bool (False: padding). Returns (indices B×S, taken B×S bool): a frame takes no more seeds once every
    remaining point coincides with a seed, or all its points are seeds. Both conditions persist (distances only
    shrink), so a frame's taken seeds come first; the loop runs on without reading its results back (no device
    synchronisation).
    """
    count = valid.sum(-1)
    seeds, gaps = [xp.zeros_like(count)], []  # gaps: each later seed's distance to the seeds before it
    dist = xp.where(valid, distance_to(seeds[0]), -xp.inf)
    for _ in range(1, min(n, valid.shape[-1])):
        gap, i = _max_argmax(dist, xp)
        seeds.append(i)
        gaps.append(gap)
        dist = xp.minimum(dist, distance_to(i))
    seeds = xp.stack(seeds, axis=-1)
    later = xp.stack(gaps, axis=-1) > 0 if gaps else seeds[:, :0] > 0
    taken = xp.arange(seeds.shape[-1]) < count[:, None]
    taken[:, 1:] &= later
    return seeds, taken


def _shift_modes(kernel: SimpleNamespace, seeds, taken, cfg: MeanShiftConfig, xp, early_stop: bool = True):
    """Mean-shift of every seed (B×S indices) over its frame's points (``kernel`` from :func:`_kernel_functions`) →
    modes B×S×(D + 2) ([μ, p]; [μ] without positions).

    A frame's modes stop moving once its taken seeds move less than 1e-4 in one iteration (embedding or position);
    with ``early_stop`` the loop ends when every frame has stopped (a host synchronisation per iteration), else it
    runs all ``cfg.iters`` iterations, which gives the same modes."""
    m = kernel.points[xp.arange(len(seeds))[:, None], seeds]
    moving = xp.ones_like(taken[:, 0])
    for _ in range(cfg.iters):
        mz, mx, wsum = kernel.moments(xp.exp(kernel.log_k(m)))
        new = mz / xp.maximum(xp.linalg.norm(mz, axis=-1, keepdims=True), 1e-12)
        if mx is not None:
            new = xp.concatenate([new, mx / xp.maximum(wsum, 1e-30)[..., None]], -1)
        shift = xp.amax(xp.abs(new - m), axis=-1)
        m = xp.where(moving[:, None, None], new, m)
        moving = moving & (xp.amax(xp.where(taken, shift, 0.0), axis=-1) >= 1e-4)
        if early_stop and not moving.any():
            break
    return m


def _find_modes(z, x, valid, pad, cfg: MeanShiftConfig, xp, static: bool = False):
    """Seeds, mean-shift and each mode's kernel density for B frames of points (z B×N×D, x B×N×2 or None, valid
    B×N bool, False at padding; ``pad``: the same, or None where no frame is padded) → (modes B×S×(D + 2) as from
    :func:`_shift_modes`, density B×S, taken B×S).
    ``static``: no early stop and the fused kernel (:func:`_kernel_functions`): nothing synchronises with the host
    and a few hundred kernels in all, what a CUDA graph captures."""
    kernel = _kernel_functions(z, x, pad, cfg.kappa, float(cfg.spatial_sigma), xp, fused=static)
    seeds, taken = _farthest_points(kernel.distance_to, valid, cfg.n_seeds, xp)
    m = _shift_modes(kernel, seeds, taken, cfg, xp, early_stop=not static)
    return m, xp.exp(kernel.log_k(m)).sum(-2), taken


_MODE_GRAPHS: dict[tuple, GraphedFunction] = {}


def _graphed_find_modes(cfg: MeanShiftConfig) -> GraphedFunction:
    """:func:`_find_modes` of torch tensors for ``cfg``, static, as a CUDA graph per batch size."""
    key = astuple(cfg)
    if key not in _MODE_GRAPHS:
        _MODE_GRAPHS[key] = GraphedFunction(
            lambda z, x, valid, pad: _find_modes(z, x, valid, pad, cfg, _namespace(z), static=True))
    return _MODE_GRAPHS[key]


def _merge_modes(mu: np.ndarray, p: np.ndarray | None, density: np.ndarray, cfg: MeanShiftConfig) -> np.ndarray:
    """Cluster id of each converged mode (S×D, S×2 or None, kernel density S): modes merge greedily, densest first,
    each into the first kept (denser) mode it is close to."""
    close = mu @ mu.T >= cfg.merge_threshold
    if p is not None:
        close &= np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1)) <= cfg.merge_xy
    close = close.tolist()
    group = [-1] * len(mu)
    kept: list[int] = []
    for s in np.argsort(-density, kind="stable").tolist():
        k = next((k for k in kept if close[s][k]), None)
        group[s] = len(kept) if k is None else group[k]
        if k is None:
            kept.append(s)
    return np.asarray(group, np.int64)


def _to_host(m, density, taken, nearest) -> tuple:
    """Modes, densities, taken flags and nearest modes (B×S×(D + 2), B×S, B×S bool, B×M int) as numpy arrays;
    tensors in one device-to-host copy."""
    if not isinstance(m, torch.Tensor):
        return m, density, taken, nearest
    b, s = taken.shape
    packed = torch.cat([torch.cat([m, density[..., None], taken[..., None].to(m.dtype)], -1).reshape(b, -1),
                        nearest.to(m.dtype)], -1).cpu().numpy()  # indices < S, exact in float32
    modes = packed[:, :s * (m.shape[-1] + 2)].reshape(b, s, -1)
    return (np.ascontiguousarray(modes[..., :-2]), np.ascontiguousarray(modes[..., -2]), modes[..., -1] > 0.5,
            packed[:, s * (m.shape[-1] + 2):].astype(np.int64))


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


def _subsample(n: int, cfg: MeanShiftConfig) -> np.ndarray:
    """Sorted indices of the at most ``cfg.max_pixels`` of n points that mode finding runs on (seeded by
    ``cfg.seed``)."""
    if n <= cfg.max_pixels:
        return np.arange(n)
    chosen = np.zeros(n, bool)  # the set numpy's choice draws, sorted in O(n)
    chosen[np.random.default_rng(cfg.seed).choice(n, cfg.max_pixels, replace=False, shuffle=False)] = True
    return np.flatnonzero(chosen)


@torch.no_grad()
def _meanshift_frames(zs: list, xs: list | None, cfg: MeanShiftConfig, xp, static: bool | None = None,
                      subs: list | None = None) -> list[np.ndarray]:
    """Cluster several frames' points at once: ``zs`` N_i×D unit embeddings (float32, N_i ≥ 1), ``xs`` N_i×2
    positions (None when ``cfg.spatial_sigma`` = 0), all numpy arrays or all tensors on one torch device; ``subs``:
    each frame's :func:`_subsample`, if already drawn.

    Returns each frame's int64 labels in [0, k_i) (numpy), ordered by cluster size (0 = largest). Mode finding runs
    on at most ``cfg.max_pixels`` points per frame; every point is then assigned its nearest mode on the device, and
    one device-to-host copy brings back modes and assignments. ``static`` (default: on CUDA): mode finding on frames
    padded to ``cfg.max_pixels`` points, so its shapes depend on the number of frames alone, as one CUDA graph
    (:mod:`~selfseg.method.cuda_graphs`; :func:`_find_modes`).
    """
    if static is None:
        static = xp is not np and zs[0].device.type == "cuda"
    subs = [_subsample(len(z), cfg) for z in zs] if subs is None else subs
    lengths = [len(s) for s in subs]
    width = cfg.max_pixels if static else 0
    valid = xp.asarray(_filled(lengths, width))
    pad = None if min(lengths) == valid.shape[-1] else valid
    z = _stack_padded([zf[xp.asarray(s)] for zf, s in zip(zs, subs)], xp, width)
    x = None if xs is None else _stack_padded([xf[xp.asarray(s)] for xf, s in zip(xs, subs)], xp, width)
    if static:
        m, density, taken = _graphed_find_modes(cfg)(z, x, valid, pad)
    else:
        m, density, taken = _find_modes(z, x, valid, pad, cfg, xp)
    d = z.shape[-1]
    # Every point's nearest taken mode (B×M), then on the host: the modes merge and clusters are ranked by size.
    log_k = _log_kernel(_stack_padded(zs, xp), None if xs is None else _stack_padded(xs, xp), m[..., :d],
                        None if x is None else m[..., d:], cfg.kappa, float(cfg.spatial_sigma), xp)
    if xp is not np or not taken.all():  # (on a device, no check: it would wait for the device)
        log_k = xp.where(taken[:, None, :], log_k, -xp.inf)
    nearest = xp.argmax(log_k, axis=-1)
    m, density, taken, nearest = _to_host(m, density, taken, nearest)
    out = []
    for f, t in enumerate(taken):
        group = np.zeros(len(t), np.int64)
        group[t] = _merge_modes(m[f, t, :d], None if x is None else m[f, t, d:], density[f, t], cfg)
        labels = group[nearest[f, :len(zs[f])]]
        rank = np.argsort(np.argsort(-np.bincount(labels), kind="stable"), kind="stable")
        out.append(rank[labels])
    return out


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
        return xp.asarray(_meanshift_frames([z], None, cfg, xp)[0])
    if xy is None or tuple(np.shape(xy)) != (n, 2):
        raise ValueError(f"spatial_sigma > 0 needs xy of shape ({n}, 2), got {None if xy is None else np.shape(xy)}")
    return xp.asarray(_meanshift_frames([z], [xp.asarray(xy, dtype=xp.float32)], cfg, xp)[0])


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
    (``static`` as in :func:`_meanshift_frames`). The host's share of the work comes before the first transfer to the
    device, so it overlaps what the device still runs (the network's forward pass)."""
    xp = _namespace(embs[0] if embs else None)
    out, pixels = [], []  # pixels: (frame index, flat indices of its foreground pixels) of non-empty frames
    for i, (emb, fg) in enumerate(zip(embs, fg_masks)):
        fg = np.asarray(fg, dtype=bool)
        if emb.ndim != 3 or tuple(emb.shape[1:]) != fg.shape:
            raise ValueError(f"emb must be D×H×W matching fg_mask H×W, got {tuple(emb.shape)} and {fg.shape}")
        out.append(np.zeros(fg.shape, np.int32))
        flat = np.flatnonzero(fg)
        if len(flat):
            pixels.append((i, flat))
    if pixels:
        subs = [_subsample(len(flat), cfg) for _, flat in pixels]
        xys = None
        if cfg.spatial_sigma > 0:  # (u, v) / max(H, W)
            xys = [np.stack(np.divmod(flat, out[i].shape[1])[::-1], 1).astype(np.float32) / float(max(out[i].shape))
                   for i, flat in pixels]
        # Transfers from here on.
        zs = [xp.asarray(embs[i], dtype=xp.float32).reshape(len(embs[i]), -1)[:, xp.asarray(flat)].T
              for i, flat in pixels]
        xs = None if xys is None else [xp.asarray(xy) for xy in xys]
        for (i, flat), labels in zip(pixels, _meanshift_frames(zs, xs, cfg, xp, static, subs)):
            out[i].reshape(-1)[flat] = labels + 1
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
