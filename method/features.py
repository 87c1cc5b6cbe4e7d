"""The network's input frames and embeddings, and segment features: the mean φ embedding of each 3D segment over
all its projected pixels in a video (the node features of the scene graphs used by graph matching).

An input frame is uint8 H×W×3 RGB, or with ``NetConfig.geometry`` ([selfseg]; the paper's φ sees RGB only) float32
H×W×7: RGB in [0, 1], the camera-frame unit normal (x right, y down, z forward; facing the camera) and the depth
about the frame's median in units of ``DEPTH_UNIT_M``, both 0 where the depth is unknown (:func:`input_frame`).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from selfseg.dataset import Video
from selfseg.method.cuda_graphs import GraphedFunction
from selfseg.method.network import GEOMETRY_CHANNELS, RGB_MEAN, EmbeddingNet
from selfseg.raycast import xyz_map

NORMAL_X = 3  # channel of the normal's x component in a geometry input frame (negated when the frame is mirrored)
NORMAL_STEP_PX = 2  # normals from the point map's differences over ± this many pixels
NORMAL_EDGE_REL = 0.05  # a neighbour's depth off by more than this fraction of the pixel's: an edge, no normal
DEPTH_UNIT_M = 0.1  # the depth channel: (depth − the frame's median depth) / DEPTH_UNIT_M


def normals_cam(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit camera-frame normals (H×W×3 float32) of a depth map (m, H×W; 0 = no depth), facing the camera: the cross
    product of the point map's central differences over ± ``NORMAL_STEP_PX``; zero where a pixel of that stencil has
    no depth or a neighbour's depth differs from the pixel's by more than ``NORMAL_EDGE_REL`` of it."""
    xyz = xyz_map(depth_m, K)
    s, (h, w) = NORMAL_STEP_PX, depth_m.shape
    pad = np.pad(xyz, ((s, s), (s, s), (0, 0)))
    right, left, down, up = pad[s:s + h, 2 * s:], pad[s:s + h, :w], pad[2 * s:, s:s + w], pad[:h, s:s + w]
    n = np.cross(right - left, down - up)
    z = xyz[..., 2]
    ok = z > 0
    for nb in (right, left, down, up):
        ok &= (nb[..., 2] > 0) & (np.abs(nb[..., 2] - z) <= NORMAL_EDGE_REL * z)
    n *= np.where(np.einsum("hwc,hwc->hw", n, xyz) > 0, -1.0, 1.0)[..., None].astype(np.float32)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok &= norm[..., 0] > 0
    return np.where(ok[..., None], n / np.maximum(norm, 1e-12), 0).astype(np.float32)


def input_frame(rgb: np.ndarray, depth_m: np.ndarray | None = None, K: np.ndarray | None = None,
                geometry: bool = False) -> np.ndarray:
    """The network's input frame (module docstring): ``rgb`` (uint8 H×W×3) itself, or with ``geometry`` float32 H×W×7
    from it, the depth (m, H×W) and ``K``."""
    if not geometry:
        return rgb
    if depth_m is None or K is None:
        raise ValueError("a network with geometry input needs the frame's depth and intrinsics")
    if depth_m.shape != rgb.shape[:2]:
        raise ValueError(f"depth is {depth_m.shape}, colour {rgb.shape[:2]}")
    valid = depth_m > 0
    rel = np.where(valid, (depth_m - (np.median(depth_m[valid]) if valid.any() else 0)) / DEPTH_UNIT_M, 0)
    return np.concatenate([rgb.astype(np.float32) / 255.0, normals_cam(depth_m, K), rel[..., None]],
                          -1).astype(np.float32)


def video_frame(video: Video, frame_id: int, geometry: bool = False) -> np.ndarray:
    """:func:`input_frame` of a video's frame (its depth read only with ``geometry``)."""
    if not geometry:
        return video.rgb(frame_id)
    return input_frame(video.rgb(frame_id), video.depth_m(frame_id), video.K(frame_id), True)


def input_fill(channels: int) -> np.ndarray:
    """float32 (channels,): the value of a masked-out input pixel: RGB_MEAN, 0 for the geometry channels."""
    if channels not in (3, 3 + GEOMETRY_CHANNELS):
        raise ValueError(f"an input frame has 3 or {3 + GEOMETRY_CHANNELS} channels, got {channels}")
    return np.concatenate([RGB_MEAN, np.zeros(channels - 3)]).astype(np.float32)


def mirror(x: torch.Tensor) -> torch.Tensor:
    """B×C×H×W input batch mirrored left-right (a geometry input's normal x negated, as the mirrored scene's)."""
    x = x.flip(-1)
    if x.shape[1] > 3:
        x[:, NORMAL_X] = -x[:, NORMAL_X]
    return x


def foreground_box(mask: np.ndarray, margin: float) -> tuple[int, int, int, int] | None:
    """Bounding box (y0, y1, x0, x1; half-open pixel ranges) of a H×W bool mask, grown on every side
    by ``margin`` × its longer side and clipped to the image; None if the mask is empty."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return None
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    pad = int(round(margin * max(y1 - y0, x1 - x0)))
    h, w = mask.shape
    return max(0, y0 - pad), min(h, y1 + pad), max(0, x0 - pad), min(w, x1 + pad)


def mask_input(x: torch.Tensor, fg_masks: list[np.ndarray] | None) -> torch.Tensor:
    """B×C×h×w network input with every pixel outside the foreground set to :func:`input_fill` (what
    ``TrainConfig.mask_background`` trains on); ``fg_masks``: B bool H×W masks, resized to h×w by nearest
    neighbour (as augment resizes them) if the input was resized. None: ``x`` unchanged."""
    return x if fg_masks is None else _masked(x, _mask_tensor(fg_masks, x.device))


def _mask_tensor(fg_masks: list[np.ndarray], device: str | torch.device) -> torch.Tensor:
    """B bool H×W masks → B×1×H×W float tensor (1 = foreground) on ``device``."""
    return torch.from_numpy(np.stack([np.asarray(f, bool) for f in fg_masks])).to(device)[:, None].float()


def _masked(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """:func:`mask_input` with the masks as a B×1×H×W float tensor."""
    if m.shape[2:] != x.shape[2:]:
        m = F.interpolate(m, size=x.shape[2:], mode="nearest")
    fill = torch.tensor(input_fill(x.shape[1]), dtype=x.dtype, device=x.device).view(1, -1, 1, 1)
    return torch.where(m > 0.5, x, fill)


def forward(net: EmbeddingNet, x: torch.Tensor, flip: bool = False) -> torch.Tensor:
    """``net(x)``; with ``flip``, the normalised mean of ``net(x)`` and the mirrored embedding of the
    mirrored input (:func:`mirror`; test-time flip averaging: mirror-equivariant, one batch of 2B)."""
    if not flip:
        return net(x)
    both = net(torch.cat([x, mirror(x)]))
    return F.normalize(both[:len(x)] + both[len(x):].flip(-1), dim=1)


def graphed_forward(net: EmbeddingNet, flip: bool = False) -> GraphedFunction:
    """:func:`forward` of an evaluation-mode ``net`` as a CUDA graph per input shape (on other devices, or with
    gradients on, a plain call). The graphs belong to the net and are keyed by where its weights are, so moving
    the net never replays a stale graph; weights changed in place are read by the next replay."""
    graphs = net.__dict__.setdefault("_cuda_graphs", {})
    key = (flip, tuple(p.data_ptr() for p in net.parameters()))
    if key not in graphs:
        graphs.clear()
        graphs[key] = GraphedFunction(lambda x: forward(net, x, flip))
    return graphs[key]


@torch.inference_mode()
def embed_frames(net: EmbeddingNet, frames: list[np.ndarray], device: str | torch.device, image_size: int = 0,
                 boxes: list[tuple[int, int, int, int] | None] | None = None,
                 fg_masks: list[np.ndarray] | None = None, flip: bool = False, square: bool = False) -> torch.Tensor:
    """Input frames (module docstring; same size) → B×D×H×W unit embeddings on ``device``.

    ``image_size`` > 0: the frames are resized so their longer side is ``image_size`` (the scale the
    network was trained at, ``TrainConfig.image_size``) and the embeddings resized back to H×W.
    ``boxes`` (foreground crops, see ``TrainConfig.fg_crop``): frame i is embedded only inside
    ``boxes[i]`` = (y0, y1, x0, x1), which is what is resized to ``image_size``; pixels outside it get
    zero vectors. A None box means the whole frame.
    ``fg_masks`` (``TrainConfig.mask_background``): bool H×W per frame; the network sees :func:`input_fill`
    outside it (:func:`mask_input`, before and after resizing, as augment does).
    ``flip``: each embedding is averaged with that of the mirrored frame (:func:`forward`).
    ``square`` (with ``boxes``, ``fg_masks`` and ``image_size`` > 0): each box is grown about its centre to a
    square of its longer side, the part beyond the frame filled with masked background, so the scale is the
    box's as without ``square`` and every crop is one image_size × image_size input: the frames run in one batch.
    Without boxes, or with square ones (one input shape), an evaluation-mode net runs as a CUDA graph on a GPU
    (:func:`graphed_forward`); plain crops differ in shape from frame to frame, so they run without graphs.
    """
    graphed = graphed_forward(net, flip) if not net.training else (lambda x: forward(net, x, flip))
    if boxes is not None and square:
        return _embed_square(net, frames, device, image_size, boxes, fg_masks, graphed)
    if boxes is not None:
        h, w = frames[0].shape[:2]
        out = torch.zeros(len(frames), net.cfg.embed_dim, h, w, device=device)
        for i, (frame, box) in enumerate(zip(frames, boxes)):
            y0, y1, x0, x1 = box if box is not None else (0, h, 0, w)
            fg = None if fg_masks is None else [np.ascontiguousarray(fg_masks[i][y0:y1, x0:x1])]
            out[i, :, y0:y1, x0:x1] = _embed(net, [np.ascontiguousarray(frame[y0:y1, x0:x1])], device, image_size, fg,
                                             lambda x: forward(net, x, flip))[0]
        return out
    return _embed(net, frames, device, image_size, fg_masks, graphed)


def _frames_tensor(frames: list[np.ndarray], device: str | torch.device) -> torch.Tensor:
    """Same-size input frames → B×C×H×W float tensor on ``device`` (uint8 RGB scaled to [0, 1])."""
    x = torch.from_numpy(np.stack(frames)).to(device).permute(0, 3, 1, 2)
    return x.float().div_(255.0) if x.dtype == torch.uint8 else x.float()


def _network_input(x: torch.Tensor, m: torch.Tensor | None, image_size: int) -> torch.Tensor:
    """B×C×h×w input frames (RGB in [0, 1]) → the network's input: background masked where ``m`` (B×1×h×w, 1 = foreground)
    is 0, resized so the longer side is ``image_size`` (≤ 0: not resized), then masked again at that size (as
    augment does). ``m`` None: nothing masked."""
    x = x if m is None else _masked(x, m)
    h, w = x.shape[2:]
    if image_size <= 0 or max(h, w) == image_size:
        return x
    s = image_size / max(h, w)
    small = F.interpolate(x, size=(max(1, round(h * s)), max(1, round(w * s))), mode="bilinear",
                          align_corners=False, antialias=s < 1)
    return small if m is None else _masked(small, m)


def _resized_embedding(emb: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """B×D×h'×w' network output → B×D×h×w unit embeddings (bilinear, renormalised; as is when h×w already)."""
    if emb.shape[2:] == (h, w):
        return emb
    return F.normalize(F.interpolate(emb, size=(h, w), mode="bilinear", align_corners=False), dim=1)


def _embed(net: EmbeddingNet, frames: list[np.ndarray], device: str | torch.device, image_size: int,
           fg_masks: list[np.ndarray] | None, run) -> torch.Tensor:
    """:func:`embed_frames` of whole frames, the network called as ``run(x)``."""
    h, w = frames[0].shape[:2]
    m = None if fg_masks is None else _mask_tensor(fg_masks, device)
    return _resized_embedding(run(_network_input(_frames_tensor(frames, device), m, image_size)), h, w)


def _embed_square(net: EmbeddingNet, frames: list[np.ndarray], device: str | torch.device, image_size: int,
                  boxes: list[tuple[int, int, int, int] | None], fg_masks: list[np.ndarray] | None,
                  run) -> torch.Tensor:
    """:func:`embed_frames` with ``square`` crops: one batch of image_size × image_size inputs, the squares cut
    and padded on ``device``."""
    if fg_masks is None or image_size <= 0:
        raise ValueError("square crops need the foreground masks (their padding is masked background) "
                         "and a training scale (image_size > 0)")
    h, w = frames[0].shape[:2]
    x, m = _frames_tensor(frames, device), _mask_tensor(fg_masks, device)
    inputs, places = [], []
    for i, box in enumerate(boxes):
        y0, y1, x0, x1 = box if box is not None else (0, h, 0, w)
        side = max(y1 - y0, x1 - x0)
        sy, sx = y0 - (side - (y1 - y0)) // 2, x0 - (side - (x1 - x0)) // 2  # the square's corner, frame pixels
        iy0, iy1, ix0, ix1 = max(sy, 0), min(sy + side, h), max(sx, 0), min(sx + side, w)  # its part in the frame
        pad = (ix0 - sx, sx + side - ix1, iy0 - sy, sy + side - iy1)  # left, right, top, bottom: mask 0 there
        inputs.append(_network_input(F.pad(x[i:i + 1, :, iy0:iy1, ix0:ix1], pad),
                                     F.pad(m[i:i + 1, :, iy0:iy1, ix0:ix1], pad), image_size))
        places.append((y0, y1, x0, x1, sy, sx, side))
    emb = run(torch.cat(inputs))
    out = torch.zeros(len(frames), net.cfg.embed_dim, h, w, device=device)
    for i, (y0, y1, x0, x1, sy, sx, side) in enumerate(places):
        out[i, :, y0:y1, x0:x1] = _resized_embedding(emb[i:i + 1], side, side)[0, :, y0 - sy:y1 - sy, x0 - sx:x1 - sx]
    return out


def segment_features(net: EmbeddingNet, video: Video, frame_ids: list[int], segmaps: dict[int, np.ndarray],
                     n_segments: int, device: str | torch.device = "cpu", batch_size: int = 4,
                     image_size: int = 0, fg_crop_margin: float | None = None,
                     fg_masks: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean embedding of every segment over all its pixels in ``frame_ids``, L2-normalised.

    segmaps: frame id → int H×W map, −1 = no segment, 0..n_segments−1 = segment id (the 3D segment
    projected into the frame). Returns (features float32 S×D, seen bool S); segments that appear in
    no frame get a zero row and ``seen = False``. ``image_size``: as in :func:`embed_frames`.
    ``fg_masks``: frame id → bool H×W foreground (``TrainConfig.mask_background``): the background is
    masked out of the input and the foreground crop box is the mask's, not the segments'.
    """
    net.eval()
    dim = net.cfg.embed_dim
    sums = torch.zeros(n_segments, dim, dtype=torch.float64, device=device)
    counts = torch.zeros(n_segments, dtype=torch.int64, device=device)
    for start in range(0, len(frame_ids), batch_size):
        fids = frame_ids[start:start + batch_size]
        maps = []
        for f in fids:
            m = np.asarray(segmaps[f])
            if m.shape != (video.height, video.width):
                raise ValueError(f"segment map of frame {f} is {m.shape}, expected {(video.height, video.width)}")
            if m.max(initial=-1) >= n_segments or m.min(initial=0) < -1:
                raise ValueError(f"segment map of frame {f} has ids outside [-1, {n_segments - 1}]")
            maps.append(m)
        fgs = None if fg_masks is None else [np.asarray(fg_masks[f], bool) for f in fids]
        boxes = None if fg_crop_margin is None else [foreground_box(m >= 0 if fgs is None else fgs[i], fg_crop_margin)
                                                     for i, m in enumerate(maps)]
        emb = embed_frames(net, [video_frame(video, f, net.cfg.geometry) for f in fids], device, image_size, boxes, fgs)  # B×D×H×W
        lab = torch.from_numpy(np.stack(maps).astype(np.int64)).to(device)
        keep = lab >= 0
        sums.index_add_(0, lab[keep], emb.permute(0, 2, 3, 1)[keep].double())
        counts += torch.bincount(lab[keep], minlength=n_segments)
    seen = counts > 0
    feats = F.normalize(sums, dim=1).float()
    return feats.cpu().numpy(), seen.cpu().numpy()
