"""The prototype contrastive loss: against a direct loop, and its gradient separates segments."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from selfseg.method.contrastive import prototype_contrastive_loss, segment_prototypes

torch.set_num_threads(2)


def loop_loss(emb: torch.Tensor, labels: torch.Tensor, tau: float, negatives: str = "batch",
              groups: list[int] | None = None) -> float:
    """Direct implementation: every pixel against every (image, segment) prototype of the batch
    ("batch") or of its own image ("image"), against one prototype per id over the batch ("global"), or
    against one prototype per (video, id) of its own video ("video", ``groups``: each image's video)."""
    protos = []
    if negatives == "global":
        for s in sorted(set(labels.flatten().tolist()) - {-1}):
            m = emb.permute(1, 0, 2, 3)[:, labels == s].mean(1)
            protos.append(((None, s), m / m.norm()))
    elif negatives == "video":
        for g in sorted(set(groups)):
            mine = torch.tensor([x == g for x in groups])
            for s in sorted(set(labels[mine].flatten().tolist()) - {-1}):
                m = emb[mine].permute(1, 0, 2, 3)[:, labels[mine] == s].mean(1)
                protos.append(((g, s), m / m.norm()))
    else:
        for b in range(emb.shape[0]):
            for s in sorted(set(labels[b].flatten().tolist()) - {-1}):
                m = emb[b][:, labels[b] == s].mean(1)
                protos.append(((b, s), m / m.norm()))
    total, count = 0.0, 0
    for b in range(emb.shape[0]):
        for y in range(emb.shape[2]):
            for x in range(emb.shape[3]):
                s = int(labels[b, y, x])
                if s < 0:
                    continue
                z = emb[b, :, y, x]
                owner = {"global": None, "video": None if groups is None else groups[b]}.get(negatives, b)
                scoped = negatives in ("image", "video")
                logits = {k: float(z @ p) / tau for k, p in protos if not scoped or k[0] == owner}
                denom = sum(math.exp(v) for v in logits.values())
                total += -(logits[(owner, s)] - math.log(denom))
                count += 1
    return total / count


def test_loss_matches_direct_loop():
    g = torch.Generator().manual_seed(0)
    emb = F.normalize(torch.randn(3, 5, 6, 7, generator=g, dtype=torch.float64), dim=1)
    labels = torch.randint(-1, 4, (3, 6, 7), generator=g)
    labels[1, :, :] = torch.where(labels[1] == 2, 7, labels[1])  # sparse ids are fine
    labels[2] = -1
    labels[2, 0, :3] = 5  # an image with a single segment
    for tau in (0.07, 0.5):
        for negatives in ("batch", "image", "global"):
            got = prototype_contrastive_loss(emb, labels, tau, negatives=negatives).item()
            assert got == pytest.approx(loop_loss(emb, labels, tau, negatives), rel=1e-9)
        for groups in ([0, 0, 1], [1, 0, 1], [0, 0, 0]):
            got = prototype_contrastive_loss(emb, labels, tau, negatives="video", groups=torch.tensor(groups)).item()
            assert got == pytest.approx(loop_loss(emb, labels, tau, "video", groups), rel=1e-9)
    # the scopes differ: per-image negatives leave out the other images' segments
    assert prototype_contrastive_loss(emb, labels, negatives="image") < prototype_contrastive_loss(emb, labels)


def test_image_negatives_do_not_push_the_same_object_in_two_images_apart():
    """Two images of the same two objects (embeddings identical across images): per-image negatives
    give the same loss as each image alone, batch negatives count the other image's copy against it."""
    g = torch.Generator().manual_seed(3)
    one = F.normalize(torch.randn(1, 4, 5, 6, generator=g, dtype=torch.float64), dim=1)
    lab = torch.zeros(1, 5, 6, dtype=torch.long)
    lab[0, :, 3:] = 1
    alone = prototype_contrastive_loss(one, lab, negatives="image").item()
    two, labs = one.repeat(2, 1, 1, 1), lab.repeat(2, 1, 1)
    assert prototype_contrastive_loss(two, labs, negatives="image").item() == pytest.approx(alone, rel=1e-12)
    assert prototype_contrastive_loss(two, labs, negatives="batch").item() > alone + 0.5


def test_global_ids_give_one_prototype_per_object_over_the_batch():
    """Object 0 in two images with different embeddings: per image two prototypes, globally one, the
    normalised mean of all its pixels in both images."""
    emb = torch.zeros(2, 2, 1, 3, dtype=torch.float64)
    emb[0, :, 0, :2] = torch.tensor([1.0, 0.0]).view(2, 1)  # image 0: object 0 on two pixels along x
    emb[1, :, 0, :1] = torch.tensor([0.0, 1.0]).view(2, 1)  # image 1: object 0 on one pixel along y
    emb[:, :, 0, 2] = torch.tensor([-1.0, 0.0])  # object 1, last pixel of both images
    labels = torch.tensor([[[0, 0, 1]], [[0, 1, 1]]])
    labels[1, 0, 1] = -1
    _, target, protos, _, proto_image = segment_prototypes(emb, labels)
    assert len(protos) == 4 and proto_image.tolist() == [0, 0, 1, 1]
    _, target, protos, _, proto_image = segment_prototypes(emb, labels, per_image=False)
    assert len(protos) == 2 and target.tolist() == [0, 0, 1, 0, 1] and proto_image.tolist() == [-1, -1]
    assert torch.allclose(protos[0], torch.tensor([2.0, 1.0], dtype=torch.float64) / math.sqrt(5))
    assert torch.allclose(protos[1], torch.tensor([-1.0, 0.0], dtype=torch.float64))


def test_global_negatives_pull_the_same_object_together_across_images():
    """Two images of objects 0 and 1 (flat, orthogonal unit embeddings e0, e1). When object 0 looks the same
    in both, the global loss is that of one image alone: its two copies share a prototype (image negatives
    would not link them, batch negatives would push them apart). When it looks e2 ⊥ e0 in image 1, its
    prototype is (e0 + e2)/√2 and its pixels score 1/√2 against it: known answers at τ = 0.5."""
    e = torch.eye(3, dtype=torch.float64)
    one = torch.zeros(1, 3, 2, 4, dtype=torch.float64)
    one[0, :, :, :2], one[0, :, :, 2:] = e[0].view(3, 1, 1), e[1].view(3, 1, 1)
    lab = torch.zeros(1, 2, 4, dtype=torch.long)
    lab[0, :, 2:] = 1
    nll = lambda own, other: math.log(1 + math.exp((other - own) / 0.5))  # noqa: E731  two prototypes
    alone = prototype_contrastive_loss(one, lab, tau=0.5, negatives="image").item()
    assert alone == pytest.approx(nll(1, 0), rel=1e-12)
    two, labs = one.repeat(2, 1, 1, 1), lab.repeat(2, 1, 1)
    assert prototype_contrastive_loss(two, labs, tau=0.5, negatives="global").item() == pytest.approx(alone, rel=1e-12)
    assert prototype_contrastive_loss(two, labs, tau=0.5, negatives="batch").item() > alone + 0.5
    apart = two.clone()
    apart[1, :, :, :2] = e[2].view(3, 1, 1)
    want = (nll(1 / math.sqrt(2), 0) + nll(1, 0)) / 2  # half the pixels are object 0's
    assert prototype_contrastive_loss(apart, labs, tau=0.5, negatives="global").item() == pytest.approx(want, rel=1e-12)
    assert prototype_contrastive_loss(apart, labs, tau=0.5, negatives="image").item() == pytest.approx(alone, rel=1e-12)


def test_video_negatives_pull_a_segments_views_together_and_leave_other_videos_alone():
    """Images 0, 1: two views of video A (segments 0, 1); image 2: video B with the same ids and the same
    embeddings as A's first view. Video scope: A's two views share a prototype per segment (when they
    look alike the loss is one image's), and B's segments are no negatives of A's pixels (adding B
    changes nothing); batch negatives push every copy apart."""
    e = torch.eye(3, dtype=torch.float64)
    one = torch.zeros(1, 3, 2, 4, dtype=torch.float64)
    one[0, :, :, :2], one[0, :, :, 2:] = e[0].view(3, 1, 1), e[1].view(3, 1, 1)
    lab = torch.zeros(1, 2, 4, dtype=torch.long)
    lab[0, :, 2:] = 1
    alone = prototype_contrastive_loss(one, lab, tau=0.5, negatives="image").item()
    three, labs = one.repeat(3, 1, 1, 1), lab.repeat(3, 1, 1)
    groups = torch.tensor([0, 0, 1])
    assert prototype_contrastive_loss(three, labs, tau=0.5, negatives="video", groups=groups).item() == \
        pytest.approx(alone, rel=1e-12)
    assert prototype_contrastive_loss(three, labs, tau=0.5, negatives="batch").item() > alone + 0.5
    apart = three.clone()
    apart[1, :, :, :2] = e[2].view(3, 1, 1)  # segment 0 of A looks e2 in A's second view: one prototype (e0+e2)/√2
    nll = lambda own, other: math.log(1 + math.exp((other - own) / 0.5))  # noqa: E731  two prototypes
    want = (2 * nll(1 / math.sqrt(2), 0) + 2 * nll(1, 0) + 2 * nll(1, 0)) / 6  # A's seg 0, A's seg 1, B
    assert prototype_contrastive_loss(apart, labs, tau=0.5, negatives="video", groups=groups).item() == \
        pytest.approx(want, rel=1e-12)
    with pytest.raises(ValueError, match="needs groups"):
        prototype_contrastive_loss(three, labs, negatives="video")
    with pytest.raises(ValueError, match="takes no groups"):
        prototype_contrastive_loss(three, labs, negatives="image", groups=groups)


def test_unknown_negatives_scope_is_refused():
    emb = F.normalize(torch.randn(1, 4, 3, 3, dtype=torch.float64), dim=1)
    with pytest.raises(ValueError, match="negatives"):
        prototype_contrastive_loss(emb, torch.zeros(1, 3, 3, dtype=torch.long), negatives="scene")


def test_pixel_subsampling_averages_over_the_drawn_pixels():
    g = torch.Generator().manual_seed(1)
    emb = F.normalize(torch.randn(2, 4, 8, 8, generator=g, dtype=torch.float64), dim=1)
    labels = torch.randint(-1, 3, (2, 8, 8), generator=g)
    full = prototype_contrastive_loss(emb, labels)
    assert prototype_contrastive_loss(emb, labels, max_pixels=10_000).item() == full.item()
    sub = prototype_contrastive_loss(emb, labels, max_pixels=20, generator=torch.Generator().manual_seed(5))
    # Per-pixel losses against the same (all-pixel) prototypes, averaged over the same random draw.
    keep = labels >= 0
    protos = {}
    for b in range(2):
        for s in labels[b].unique().tolist():
            if s >= 0:
                protos[(b, s)] = F.normalize(emb[b][:, labels[b] == s].mean(1), dim=0)
    keys = sorted(protos)
    z = emb.permute(0, 2, 3, 1)[keep]
    img = torch.arange(2).view(2, 1, 1).expand_as(labels)[keep]
    target = torch.tensor([keys.index((int(b), int(s))) for b, s in zip(img, labels[keep])])
    per_pixel = F.cross_entropy(z @ torch.stack([protos[k] for k in keys]).t() / 0.07, target, reduction="none")
    pick = torch.randperm(len(target), generator=torch.Generator().manual_seed(5))[:20]
    assert sub.item() == pytest.approx(per_pixel[pick].mean().item(), rel=1e-12)
    assert sub.item() != pytest.approx(full.item(), rel=1e-6)


def test_loss_ignores_background_and_handles_empty():
    emb = F.normalize(torch.randn(1, 4, 5, 5, dtype=torch.float64), dim=1).requires_grad_()
    labels = torch.full((1, 5, 5), -1)
    loss = prototype_contrastive_loss(emb, labels)
    assert loss.item() == 0.0
    loss.backward()
    assert torch.all(emb.grad == 0)
    labels[0, :2] = 0
    labels[0, 3:] = 1
    prototype_contrastive_loss(emb, labels).backward()
    assert torch.all(emb.grad[0, :, 2] == 0) and emb.grad[0, :, :2].abs().sum() > 0  # row 2 is background


def test_gradient_separates_two_flat_segments():
    """A tiny conv net sees two flat-coloured halves; a few steps make their embeddings dissimilar."""
    torch.manual_seed(0)
    img = torch.zeros(1, 3, 16, 16)
    img[0, :, :, :8] = torch.tensor([0.8, 0.2, 0.2]).view(3, 1, 1)
    img[0, :, :, 8:] = torch.tensor([0.25, 0.3, 0.75]).view(3, 1, 1)
    labels = torch.zeros(1, 16, 16, dtype=torch.long)
    labels[0, :, 8:] = 1
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 16, 1), torch.nn.ReLU(), torch.nn.Conv2d(16, 8, 1))

    def cos_between_segments():
        with torch.no_grad():
            z = F.normalize(net(img), dim=1)[0]
        a, b = F.normalize(z[:, :, :8].mean((1, 2)), dim=0), F.normalize(z[:, :, 8:].mean((1, 2)), dim=0)
        return float(a @ b)

    before = cos_between_segments()
    opt = torch.optim.Adam(net.parameters(), lr=0.05)
    losses = []
    for _ in range(30):
        loss = prototype_contrastive_loss(F.normalize(net(img), dim=1), labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    after = cos_between_segments()
    assert before > 0.9  # similar colours start out with nearly identical embeddings
    assert after < 0.3  # at τ = 0.07 the loss is ~0 once the prototypes are this far apart
    assert losses[-1] < 0.1 * losses[0]
    # Same-segment pixels are pulled together: within-segment cosine to the prototype is near 1.
    with torch.no_grad():
        z = F.normalize(net(img), dim=1)[0]
    proto = F.normalize(z[:, :, :8].mean((1, 2)), dim=0)
    assert float((proto[:, None, None] * z[:, :, :8]).sum(0).min()) > 0.99
    assert np.isfinite(losses).all()
