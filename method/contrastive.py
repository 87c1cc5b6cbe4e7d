"""Pixel-to-prototype contrastive loss (the MaskContrast idea, O(P·N) instead of O(P²)).

For a labelled pixel k of segment i: ``L_k = −log(exp(z_k·z̄_i/τ) / Σ_j exp(z_k·z̄_j/τ))``, where
z̄_j is the L2-normalised mean embedding of segment j. Which segments j runs over is the scope of
the negatives:

- ``"image"`` (the paper's "j = 1..N, N = the number of segments" of the pixel's own scene/frame):
  only the other segments of the pixel's own image;
- ``"batch"``: every segment of every image in the batch. Segment ids are per image, so the same
  object seen in two images of a batch is then a negative of itself;
- ``"global"``: ids are global, shared by every image of the batch (object identities, e.g. the
  supervised bound's object ids): one prototype per id over the whole batch, pulled together
  across images, and every other id of the batch as a negative;
- ``"video"`` (**[selfseg]**, not the paper's): ids name the same 3-D segment in every frame of one
  video, and each image carries its video (``groups``): one prototype per (video, segment) over the
  batch, so a segment's views in two frames are pulled together, and only the segments of the
  pixel's own video are negatives (the same object in another scene is never pushed away).

Prototypes are not detached: gradients flow through them as well.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


NEGATIVES = ("image", "batch", "global", "video")


def segment_prototypes(emb: torch.Tensor, labels: torch.Tensor, per_image: bool = True,
                       groups: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-segment normalised mean embeddings over a batch.

    emb: B×D×H×W; labels: B×H×W long, −1 = ignore, ≥ 0 = segment id within its owner: its image
    (``per_image``), its group (``groups``: B long, e.g. each image's video) or the whole batch (neither).
    Returns (z: P×D embeddings of the labelled pixels, target: P long index into the prototypes,
    protos: N×D normalised prototypes, one per (owner, segment id) pair present, pixel_owner: P long
    owner of each pixel (image index, or group), proto_owner: N long owner of each prototype; −1 for
    every pixel and prototype when ids are global to the batch).
    """
    if emb.ndim != 4 or labels.shape != (emb.shape[0],) + emb.shape[2:]:
        raise ValueError(f"emb must be B×D×H×W and labels B×H×W, got {tuple(emb.shape)} and {tuple(labels.shape)}")
    b, d = emb.shape[:2]
    if groups is not None and tuple(groups.shape) != (b,):
        raise ValueError(f"groups must hold one owner per image ({b}), got shape {tuple(groups.shape)}")
    labels = labels.long()
    keep = labels >= 0
    z = emb.permute(0, 2, 3, 1)[keep]  # P×D
    if groups is not None:
        owners = groups.long().to(labels.device)
    elif per_image:
        owners = torch.arange(b, device=labels.device)
    else:
        owners = torch.full((b,), -1, dtype=torch.long, device=labels.device)
    owner = owners.view(b, 1, 1).expand_as(labels)[keep]
    stride = int(labels.max().clamp(min=0)) + 1
    key = (owner + 1) * stride + labels[keep]  # owners ≥ −1
    uniq, target = torch.unique(key, return_inverse=True)
    n = int(target.max()) + 1 if target.numel() else 0
    sums = torch.zeros(n, d, dtype=emb.dtype, device=emb.device).index_add_(0, target, z)
    return z, target, F.normalize(sums, dim=1), owner, uniq // stride - 1


def prototype_contrastive_loss(emb: torch.Tensor, labels: torch.Tensor, tau: float = 0.07, max_pixels: int = 0,
                               generator: torch.Generator | None = None, negatives: str = "batch",
                               groups: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over labelled pixels of the pixel-to-prototype InfoNCE loss (scalar).

    emb: B×D×H×W, L2-normalised per pixel; labels: B×H×W long (−1 = ignore/background,
    ≥ 0 = segment id, unique within each image; with ``negatives="global"`` an id names the same
    segment in every image of the batch). Returns 0 (with a graph) if nothing is labelled.
    ``max_pixels`` > 0 bounds memory: prototypes use every pixel, but the loss is averaged over a
    random subset of that many labelled pixels (drawn with ``generator``, a CPU generator).
    ``negatives``: "image", "batch", "global" or "video", the scope of the softmax's denominator (module
    docstring); ``groups`` (B long, each image's video) is what "video" needs and the others refuse.
    """
    if tau <= 0:
        raise ValueError(f"tau must be positive, got {tau}")
    if negatives not in NEGATIVES:
        raise ValueError(f"negatives must be one of {NEGATIVES}, got {negatives!r}")
    if (groups is None) == (negatives == "video"):
        need = "needs" if groups is None else "takes no"
        raise ValueError(f"negatives {negatives!r} {need} groups (each image's video)")
    z, target, protos, pixel_owner, proto_owner = segment_prototypes(emb, labels, per_image=negatives != "global",
                                                                     groups=groups)
    if target.numel() == 0:
        return emb.sum() * 0.0
    if 0 < max_pixels < len(target):
        pick = torch.randperm(len(target), generator=generator)[:max_pixels].to(target.device)
        z, target, pixel_owner = z[pick], target[pick], pixel_owner[pick]
    logits = z @ protos.t() / tau
    if negatives in ("image", "video"):
        logits = logits.masked_fill(pixel_owner[:, None] != proto_owner[None, :], float("-inf"))
    return F.cross_entropy(logits, target)
