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
  across images, and every other id of the batch as a negative.

Prototypes are not detached: gradients flow through them as well.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


NEGATIVES = ("image", "batch", "global")


def segment_prototypes(emb: torch.Tensor, labels: torch.Tensor, per_image: bool = True
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-segment normalised mean embeddings over a batch.

    emb: B×D×H×W; labels: B×H×W long, −1 = ignore, ≥ 0 = segment id within its image
    (``per_image``) or shared by the whole batch (not ``per_image``).
    Returns (z: P×D embeddings of the labelled pixels, target: P long index into the prototypes,
    protos: N×D normalised prototypes, one per (image, segment id) pair present, or per id present
    if not ``per_image``, pixel_image: P long image index of each pixel, proto_image: N long image
    index of each prototype; −1 for every prototype if not ``per_image``).
    """
    if emb.ndim != 4 or labels.shape != (emb.shape[0],) + emb.shape[2:]:
        raise ValueError(f"emb must be B×D×H×W and labels B×H×W, got {tuple(emb.shape)} and {tuple(labels.shape)}")
    b, d = emb.shape[:2]
    labels = labels.long()
    keep = labels >= 0
    z = emb.permute(0, 2, 3, 1)[keep]  # P×D
    image = torch.arange(b, device=labels.device).view(b, 1, 1).expand_as(labels)[keep]
    stride = int(labels.max().clamp(min=0)) + 1
    key = image * stride + labels[keep] if per_image else labels[keep]
    uniq, target = torch.unique(key, return_inverse=True)
    n = int(target.max()) + 1 if target.numel() else 0
    sums = torch.zeros(n, d, dtype=emb.dtype, device=emb.device).index_add_(0, target, z)
    proto_image = uniq // stride if per_image else torch.full_like(uniq, -1)
    return z, target, F.normalize(sums, dim=1), image, proto_image


def prototype_contrastive_loss(emb: torch.Tensor, labels: torch.Tensor, tau: float = 0.07, max_pixels: int = 0,
                               generator: torch.Generator | None = None, negatives: str = "batch") -> torch.Tensor:
    """Mean over labelled pixels of the pixel-to-prototype InfoNCE loss (scalar).

    emb: B×D×H×W, L2-normalised per pixel; labels: B×H×W long (−1 = ignore/background,
    ≥ 0 = segment id, unique within each image; with ``negatives="global"`` an id names the same
    segment in every image of the batch). Returns 0 (with a graph) if nothing is labelled.
    ``max_pixels`` > 0 bounds memory: prototypes use every pixel, but the loss is averaged over a
    random subset of that many labelled pixels (drawn with ``generator``, a CPU generator).
    ``negatives``: "image", "batch" or "global", the scope of the softmax's denominator (module docstring).
    """
    if tau <= 0:
        raise ValueError(f"tau must be positive, got {tau}")
    if negatives not in NEGATIVES:
        raise ValueError(f"negatives must be one of {NEGATIVES}, got {negatives!r}")
    z, target, protos, pixel_image, proto_image = segment_prototypes(emb, labels, per_image=negatives != "global")
    if target.numel() == 0:
        return emb.sum() * 0.0
    if 0 < max_pixels < len(target):
        pick = torch.randperm(len(target), generator=generator)[:max_pixels].to(target.device)
        z, target, pixel_image = z[pick], target[pick], pixel_image[pick]
    logits = z @ protos.t() / tau
    if negatives == "image":
        logits = logits.masked_fill(pixel_image[:, None] != proto_image[None, :], float("-inf"))
    return F.cross_entropy(logits, target)
