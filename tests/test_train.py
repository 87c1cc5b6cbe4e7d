"""The embedding trainer (augmentation, checkpoints, resume), segment features, and the supervised method."""
import json
import threading

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from selfseg.analytic import make_dataset, two_box_scenes
from selfseg.dataset import Dataset, DatasetError
from selfseg.guard import ground_truth_forbidden
from selfseg.method.embed_method import EmbeddingMethodConfig
from selfseg.method.features import embed_frames, foreground_box, mask_input, segment_features
from selfseg.method.meanshift import MeanShiftConfig
from selfseg.method.network import RGB_MEAN, EmbeddingNet, NetConfig
from selfseg.method.train import (FrameLabelSource, TrainConfig, at_output_stride, augment, batch_items,
                                  load_embedding_net, make_batch, train_embedding, training_batches)
from selfseg.method import train as train_module
from selfseg.registry import get_method_class

torch.set_num_threads(2)
SMALL_NET = NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16)


class SyntheticSource:
    """64×48 images of 2–3 flat-coloured rectangles; labels = rectangle index. Can simulate a crash."""

    def __init__(self, n=6, crash_after=None):
        rng = np.random.default_rng(0)
        self.items = []
        for _ in range(n):
            rgb = np.full((48, 64, 3), 200, np.uint8)
            lab = np.full((48, 64), -1, np.int32)
            for k in range(int(rng.integers(2, 4))):
                y, x = rng.integers(0, 30), rng.integers(0, 44)
                rgb[y:y + 18, x:x + 20] = rng.integers(0, 255, 3)
                lab[y:y + 18, x:x + 20] = k
            self.items.append((rgb, lab))
        self.calls, self.crash_after = 0, crash_after

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        self.calls += 1
        if self.crash_after is not None and self.calls > self.crash_after:
            raise KeyboardInterrupt("simulated crash")
        return self.items[i]


def tiny_cfg(**kw):
    base = dict(steps=6, batch_size=2, image_size=0, crop=(32, 48), checkpoint_every=3, lr=5e-3, seed=3, threads=2)
    return TrainConfig(**{**base, **kw})


def test_augment_keeps_labels_aligned_with_pixels():
    rgb = np.zeros((48, 64, 3), np.uint8)
    lab = np.full((48, 64), -1, np.int32)
    for k, (y, x) in enumerate([(0, 0), (0, 32), (24, 0), (24, 32)]):
        rgb[y:y + 24, x:x + 32] = (60 * k + 20, 10, 250 - 60 * k)
        lab[y:y + 24, x:x + 32] = k
    lab[24:, 32:] = -1
    cfg = TrainConfig(image_size=80, crop=(56, 72), scale_range=(0.6, 1.4), brightness=0, contrast=0, saturation=0,
                      hue=0, min_segment_px=1)
    for step in range(8):
        img, out = augment(rgb, lab, cfg, np.random.default_rng(step))
        assert img.shape == (3, 56, 72) and out.shape == (56, 72) and img.dtype == np.float32
        red = img[0]
        for k in np.unique(out[out >= 0]):
            vals = red[(out == k)]
            interior = np.abs(vals - (60 * k + 20) / 255) < 0.02
            assert interior.mean() > 0.8  # label k sits on colour k (edges blur by interpolation)


def test_foreground_box_grows_by_the_margin_and_clips():
    mask = np.zeros((100, 200), bool)
    mask[40:60, 50:90] = True  # 20 × 40 px
    assert foreground_box(mask, 0.0) == (40, 60, 50, 90)
    assert foreground_box(mask, 0.25) == (30, 70, 40, 100)  # 0.25 × 40 = 10 px on every side
    assert foreground_box(mask, 2.0) == (0, 100, 0, 170)
    assert foreground_box(np.zeros((4, 4), bool), 0.1) is None


def test_fg_crop_sets_the_scale_of_the_objects_not_the_frame():
    """A 16×16 object in a 240×320 frame: with fg_crop it fills the 64-px training image, without it
    it stays a few pixels wide."""
    rgb = np.zeros((240, 320, 3), np.uint8)
    lab = np.full((240, 320), -1, np.int32)
    lab[100:116, 200:216] = 0
    rgb[100:116, 200:216] = 255
    common = dict(image_size=64, crop=(64, 64), scale_range=(1, 1), flip=False, brightness=0, contrast=0,
                  saturation=0, hue=0, min_segment_px=1)
    _, plain = augment(rgb, lab, TrainConfig(**common), np.random.default_rng(0))
    img, crop = augment(rgb, lab, TrainConfig(fg_crop=True, fg_crop_margin=0.1, **common), np.random.default_rng(0))
    assert (plain >= 0).sum() <= 16
    assert (crop >= 0).sum() > 0.6 * 64 * 64
    assert np.abs(img[0][crop >= 0] - 1.0).mean() < 0.05  # the label still sits on the object's pixels


def test_embedding_inside_a_box_equals_embedding_the_crop():
    torch.manual_seed(0)
    net = EmbeddingNet(NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8)).eval()
    rgb = np.random.default_rng(0).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    box = (10, 42, 20, 68)
    full = embed_frames(net, [rgb], "cpu", 96, [box])[0]
    crop = embed_frames(net, [np.ascontiguousarray(rgb[10:42, 20:68])], "cpu", 96)[0]
    assert torch.allclose(full[:, 10:42, 20:68], crop, atol=1e-6)
    assert float(full[:, :10].abs().max()) == 0.0 and float(full[:, :, 68:].abs().max()) == 0.0


def test_flip_averaging_makes_the_embedding_mirror_equivariant():
    """With ``flip``, the mirrored frame embeds to the mirrored embedding (the network alone does not), over the
    whole frame and inside a foreground box at another scale, in unit vectors."""
    torch.manual_seed(0)
    net = EmbeddingNet(NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8)).eval()
    rgb = np.random.default_rng(0).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    mirror = np.ascontiguousarray(rgb[:, ::-1])
    for size, box, mirror_box in ((0, None, None), (96, [(10, 42, 20, 68)], [(10, 42, 12, 60)])):
        plain = embed_frames(net, [rgb], "cpu", size, box)[0]
        assert not torch.allclose(embed_frames(net, [mirror], "cpu", size, mirror_box)[0], plain.flip(-1), atol=1e-3)
        avg = embed_frames(net, [rgb], "cpu", size, box, flip=True)[0]
        assert torch.allclose(embed_frames(net, [mirror], "cpu", size, mirror_box, flip=True)[0], avg.flip(-1),
                              atol=1e-5)
        inside = avg if box is None else avg[:, 10:42, 20:68]
        assert torch.allclose(inside.norm(dim=0), torch.ones(inside.shape[1:]), atol=1e-5)
        assert not torch.allclose(avg, plain, atol=1e-3)


def test_augment_jitter_changes_colour_only_and_drops_small_segments():
    rgb = np.full((48, 64, 3), 128, np.uint8)
    lab = np.zeros((48, 64), np.int32)
    lab[:2, :2] = 1  # 4 pixels: below min_segment_px
    cfg = TrainConfig(image_size=0, crop=(48, 64), scale_range=(1, 1), flip=False, min_segment_px=16)
    img, out = augment(rgb, lab, cfg, np.random.default_rng(0))
    assert np.all(out[:2, :2] == -1) and np.all(out[2:] == 0)
    assert abs(float(img.mean()) - 128 / 255) > 1e-3 and 0 <= img.min() and img.max() <= 1


def _plain(**kw) -> TrainConfig:
    """Augmentation that only crops (scale 1, no flip, no jitter) unless ``kw`` says otherwise."""
    base = dict(image_size=0, crop=(48, 64), scale_range=(1, 1), flip=False, brightness=0, contrast=0, saturation=0,
                hue=0, min_segment_px=1)
    return TrainConfig(**{**base, **kw})


def _two_objects():
    """48×64 random texture (the 'table') with objects 0 and 1; the given foreground covers object 0, the left
    half of object 1 and an unlabelled patch."""
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    lab = np.full((48, 64), -1, np.int32)
    lab[5:20, 5:25], lab[25:40, 30:60] = 0, 1
    fg = np.zeros((48, 64), bool)
    fg[5:20, 5:25], fg[25:40, 30:45], fg[0:4, 50:60] = True, True, True
    return rgb, lab, fg


def test_mask_background_sets_exactly_the_background_pixels():
    rgb, lab, fg = _two_objects()
    mean = np.asarray(RGB_MEAN, np.float32)[:, None]
    img, out = augment(rgb, lab, _plain(mask_background=True), np.random.default_rng(0), fg)
    assert np.array_equal(img[:, ~fg], np.repeat(mean, (~fg).sum(), 1))  # every background pixel: the mean
    assert np.allclose(img[:, fg], (rgb[fg].astype(np.float32) / 255.0).T, atol=1e-6)  # the foreground untouched
    assert np.array_equal(out, np.where(fg, lab, -1))  # labels outside the given foreground are ignored
    # without a foreground mask the labelled pixels are the foreground
    img, out = augment(rgb, lab, _plain(mask_background=True), np.random.default_rng(0))
    assert np.array_equal(img[:, lab < 0], np.repeat(mean, (lab < 0).sum(), 1)) and np.array_equal(out, lab)
    # colour jitter changes the foreground, never the mask value
    img, _ = augment(rgb, lab, _plain(mask_background=True, brightness=0.4, hue=0.1), np.random.default_rng(0), fg)
    assert np.array_equal(img[:, ~fg], np.repeat(mean, (~fg).sum(), 1))
    assert not np.allclose(img[:, fg], (rgb[fg].astype(np.float32) / 255.0).T, atol=0.01)
    # off: the table stays in the input
    img, _ = augment(rgb, lab, _plain(), np.random.default_rng(0), fg)
    assert np.allclose(img, rgb.astype(np.float32).transpose(2, 0, 1) / 255.0, atol=1e-6)


def test_mask_background_crops_to_the_given_foreground():
    """The crop box is the given foreground's: its unlabelled red patch (rows 0–3) is in the training image
    and not masked; with the labelled pixels as foreground (no mask given) it is cut off."""
    rgb, lab, fg = _two_objects()
    rgb[0:4, 50:60] = (255, 0, 0)
    cfg = _plain(mask_background=True, fg_crop=True, fg_crop_margin=0.0, image_size=64, crop=(48, 64))
    red = lambda img: (img[0] > 0.9) & (img[1] < 0.1) & (img[2] < 0.1)  # noqa: E731
    img, out = augment(rgb, lab, cfg, np.random.default_rng(0), fg)  # box 40 × 55 px → 47 × 64
    assert img.shape == (3, 48, 64) and (out == 1).any() and (out == 0).any()
    assert red(img).sum() >= 30 and (out[red(img)] == -1).mean() > 0.9  # the patch: seen, unlabelled
    img, _ = augment(rgb, lab, cfg, np.random.default_rng(0))
    assert red(img).sum() < 3


def test_padding_gets_the_ignore_label_and_with_masking_the_mask_value():
    """A frame scaled to 24×32 inside a 40×48 crop: the padding is ignored; black without masking (as
    before), the mask value with it, so the network cannot tell padding from background."""
    rgb, lab, fg = _two_objects()
    lab[:] = 0  # everything labelled: only the padding can be ignored
    mean = np.asarray(RGB_MEAN, np.float32)
    for mask in (False, True):
        img, out = augment(rgb, lab, _plain(image_size=32, crop=(40, 48), mask_background=mask),
                           np.random.default_rng(0), np.ones((48, 64), bool))
        assert np.all(out[24:] == -1) and np.all(out[:, 32:] == -1) and np.all(out[:24, :32] == 0)
        pad = img[:, 24:, :].reshape(3, -1).T
        assert np.all(pad == (mean if mask else 0))
        assert np.all(img[:, :, 32:].reshape(3, -1).T == (mean if mask else 0))


def test_rotation_keeps_labels_on_their_pixels_and_ignores_what_rotates_in():
    rgb = np.zeros((48, 64, 3), np.uint8)
    lab = np.zeros((48, 64), np.int32)
    for k, (y, x) in enumerate([(0, 0), (0, 32), (24, 0), (24, 32)]):
        rgb[y:y + 24, x:x + 32] = (60 * k + 20, 10, 250 - 60 * k)
        lab[y:y + 24, x:x + 32] = k
    cfg = _plain(rotation_deg=40)
    turned = 0
    for step in range(6):
        img, out = augment(rgb, lab, cfg, np.random.default_rng(step))
        assert (out[0, 0] == -1) == (out[-1, -1] == -1)  # corners come in from outside (or none do at ~0°)
        turned += int(out[0, 0] == -1)
        for k in np.unique(out[out >= 0]):
            interior = np.abs(img[0][out == k] - (60 * k + 20) / 255) < 0.02
            assert interior.mean() > 0.8  # label k sits on colour k (edges blur by interpolation)
    assert turned >= 4 and not np.array_equal(out, lab)


def test_masked_embedding_does_not_see_the_background():
    """With the foreground mask, frames that differ only outside it embed identically (whole frame, at
    another scale, and inside a foreground box); without it they do not."""
    torch.manual_seed(0)
    net = EmbeddingNet(NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8)).eval()
    rgb, _, fg = _two_objects()
    other = np.random.default_rng(7).integers(0, 256, rgb.shape, dtype=np.uint8)
    other[fg] = rgb[fg]
    box = foreground_box(fg, 0.1)
    for size, boxes in ((0, None), (96, None), (96, [box])):
        a = embed_frames(net, [rgb], "cpu", size, boxes, [fg])
        b = embed_frames(net, [other], "cpu", size, boxes, [fg])
        assert torch.equal(a, b)
        assert not torch.allclose(embed_frames(net, [rgb], "cpu", size, boxes), embed_frames(net, [other], "cpu",
                                                                                             size, boxes))
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    want = torch.where(torch.from_numpy(fg), x, torch.tensor(RGB_MEAN).view(1, 3, 1, 1))
    assert torch.equal(mask_input(x, [fg]), want)


def test_square_crops_run_as_one_batch_at_the_boxes_scale():
    """Square crops: every frame one image_size² input in one network call (plain crops: one call per frame,
    each its own shape); a box that is already square and inside the frame embeds as the plain crop does; a box
    at the frame's edge pads with masked background (the frame outside the mask is not seen); nothing outside
    the box is embedded."""
    torch.manual_seed(0)
    net = EmbeddingNet(NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8)).eval()
    shapes = []
    net.register_forward_pre_hook(lambda module, args: shapes.append(tuple(args[0].shape)))
    rgb, _, fg = _two_objects()
    wide = np.zeros_like(fg)
    wide[30:40, 4:60] = True  # box 10 × 56 px → a 56-px square running off the frame's bottom
    sq = np.zeros_like(fg)
    sq[10:30, 20:40] = True  # box 20 × 20 px, inside the frame
    boxes = [foreground_box(m, 0.0) for m in (wide, sq)]
    emb = embed_frames(net, [rgb, rgb], "cpu", 32, boxes, [wide, sq], square=True)
    assert shapes == [(2, 3, 32, 32)]
    shapes.clear()
    plain = embed_frames(net, [rgb, rgb], "cpu", 32, boxes, [wide, sq])
    assert shapes == [(1, 3, 6, 32), (1, 3, 32, 32)]
    assert torch.allclose(emb[1], plain[1], atol=1e-5)  # square box: the same input, so the same embedding
    assert not torch.allclose(emb[0], plain[0], atol=1e-3)  # a 6 × 32 input against a padded 32 × 32 one
    for i, (y0, y1, x0, x1) in enumerate(boxes):
        inside = torch.zeros(48, 64, dtype=torch.bool)
        inside[y0:y1, x0:x1] = True
        assert torch.allclose(emb[i][:, inside].norm(dim=0), torch.ones(int(inside.sum())), atol=1e-5)
        assert torch.all(emb[i][:, ~inside] == 0)
    other = np.random.default_rng(7).integers(0, 256, rgb.shape, dtype=np.uint8)
    other[wide] = rgb[wide]
    assert torch.equal(embed_frames(net, [other], "cpu", 32, boxes[:1], [wide], square=True),
                       embed_frames(net, [rgb], "cpu", 32, boxes[:1], [wide], square=True))
    with pytest.raises(ValueError, match="foreground masks"):
        embed_frames(net, [rgb], "cpu", 32, boxes[:1], square=True)
    with pytest.raises(ValueError, match="test_square_crop needs"):
        EmbeddingMethodConfig(train=TrainConfig(fg_crop=True), test_square_crop=True)


def test_batches_made_ahead_in_threads_are_the_serial_batches():
    """training_batches with a thread pool yields, in step order, exactly the batches made one by one (a batch is
    a pure function of (seed, step)); resuming at a later step starts there; the pool is shut down when the
    consumer stops early."""
    rgb, lab, fg = _two_objects()
    cfg = _plain(batch_size=3, crop=(32, 48), image_size=48, scale_range=(0.75, 1.25), flip=True, brightness=0.3,
                 hue=0.05)
    source = [(rgb, lab), (rgb[::-1].copy(), lab[::-1].copy())]
    serial = list(training_batches(source, cfg, range(2, 9)))
    threaded = list(training_batches(source, cfg, range(2, 9), threads=3))
    assert len(serial) == len(threaded) == 7
    for a, b in zip(serial, threaded):
        assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not torch.equal(serial[0][0], serial[1][0])  # the steps differ
    assert all(torch.equal(x, y) for x, y in zip(serial[3], make_batch(source, cfg, 5)))
    early = training_batches(source, cfg, range(100), threads=2)
    next(early)
    early.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("batches")]


def test_make_batch_masks_with_the_sources_foreground(analytic_dataset):
    """FrameLabelSource's foreground loader is what mask_background masks with (not its labels)."""
    video = Dataset(analytic_dataset).labeled("000000")
    fid = video.frame_ids[0]
    half = np.zeros((video.height, video.width), bool)
    half[:, :video.width // 2] = True
    labels = lambda v, f: v.inst(f).astype(np.int32) - 1  # noqa: E731
    src = FrameLabelSource([(video, fid, labels)], foreground=lambda v, f: half & (v.inst(f) > 0))
    fg = src.foreground(0)
    assert 0 < fg.sum() < (src[0][1] >= 0).sum()
    cfg = _plain(mask_background=True, crop=(video.height, video.width), batch_size=2)
    rgb, lab, _ = make_batch(src, cfg, step=0)
    for i in range(2):
        assert np.array_equal(lab[i].numpy(), np.where(fg, src[0][1], -1))
        assert torch.all(rgb[i][:, torch.from_numpy(~fg)] == torch.tensor(RGB_MEAN).view(3, 1))
    rgb, lab, _ = make_batch(src, _plain(crop=(video.height, video.width), batch_size=1), step=0)  # off: not read
    assert np.array_equal(lab[0].numpy(), src[0][1])
    bad = FrameLabelSource([(video, fid, labels)], foreground=lambda v, f: np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="foreground mask"):
        bad.foreground(0)
    assert FrameLabelSource([(video, fid, labels)]).foreground(0) is None
    assert src.group(0) == video.video_id


class VideoSource(SyntheticSource):
    """SyntheticSource whose pairs belong to videos: pair i is a frame of video ``"v{i % videos}"``."""

    def __init__(self, n=12, videos=4):
        super().__init__(n)
        self.videos = videos

    def group(self, i):
        return f"v{i % self.videos}"


def test_frames_per_video_draws_k_frames_of_each_of_b_over_k_videos():
    src = VideoSource(n=12, videos=4)
    for step in range(5):
        cfg = tiny_cfg(batch_size=6, frames_per_video=2)
        idx, groups = batch_items(src, cfg, np.random.default_rng([cfg.seed, step]))
        assert groups.tolist() == [0, 0, 1, 1, 2, 2]
        videos = [src.group(int(i)) for i in idx]
        assert [videos[2 * j] == videos[2 * j + 1] for j in range(3)] == [True] * 3
        assert len(set(videos)) == 3  # 3 of the 4 videos, without replacement
        assert all(idx[2 * j] != idx[2 * j + 1] for j in range(3))  # each video has 3 frames: 2 distinct ones
        _, labels, g = make_batch(src, cfg, step)
        assert g.tolist() == groups.tolist() and labels.shape[0] == 6
    idx, groups = batch_items(src, tiny_cfg(batch_size=4), np.random.default_rng(0))  # k = 1: its own group each
    assert groups.tolist() == [0, 1, 2, 3] and len(idx) == 4
    with pytest.raises(ValueError, match="group"):
        batch_items(SyntheticSource(), tiny_cfg(batch_size=4, frames_per_video=2), np.random.default_rng(0))
    with pytest.raises(ValueError, match="divide batch_size"):
        tiny_cfg(batch_size=6, frames_per_video=4)
    with pytest.raises(ValueError, match="frames_per_video ≥ 2"):
        tiny_cfg(negatives="video")


def test_video_negatives_train_and_their_loss_differs_from_image_negatives(tmp_path):
    """A run with negatives 'video' trains (finite, falling loss) and is another run than 'image' with the
    same frames: the same batches (same seed and frames_per_video), another loss."""
    src = VideoSource(n=12, videos=3)
    logs = {}
    for neg in ("image", "video"):
        cfg = tiny_cfg(steps=8, batch_size=4, frames_per_video=2, negatives=neg, checkpoint_every=8)
        train_embedding(src, cfg, SMALL_NET, tmp_path / neg, progress=False)
        logs[neg] = json.loads((tmp_path / neg / "training_log.json").read_text())["loss"]
    assert all(np.isfinite(logs["video"])) and np.mean(logs["video"][-3:]) < np.mean(logs["video"][:3])
    assert logs["video"][0] != pytest.approx(logs["image"][0], rel=1e-6)


def test_global_negatives_need_a_source_with_global_ids(tmp_path):
    with pytest.raises(ValueError, match="global"):
        train_embedding(SyntheticSource(), tiny_cfg(negatives="global"), SMALL_NET, tmp_path, progress=False)


def test_resumed_training_equals_unbroken_run(tmp_path):
    cfg = tiny_cfg()
    w_full = train_embedding(SyntheticSource(), cfg, SMALL_NET, tmp_path / "full", progress=False)
    crashing = SyntheticSource(crash_after=2 * 4)  # crashes in step 5, after the step-3 checkpoint
    with pytest.raises(KeyboardInterrupt):
        train_embedding(crashing, cfg, SMALL_NET, tmp_path / "resumed", progress=False)
    assert [p.name for p in (tmp_path / "resumed" / "checkpoints").iterdir()] == ["step_000003.pt"]
    assert not (tmp_path / "resumed" / "weights.pt").exists()
    resumed_source = SyntheticSource()
    w_res = train_embedding(resumed_source, cfg, SMALL_NET, tmp_path / "resumed", progress=False)
    assert resumed_source.calls == 3 * cfg.batch_size  # only steps 4–6 ran
    a = torch.load(w_full, weights_only=True)["state_dict"]
    b = torch.load(w_res, weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    log_a = json.loads((tmp_path / "full" / "training_log.json").read_text())
    log_b = json.loads((tmp_path / "resumed" / "training_log.json").read_text())
    assert log_a["loss"] == log_b["loss"] and len(log_a["loss"]) == 6
    assert not (tmp_path / "full" / "checkpoints").exists() and not (tmp_path / "resumed" / "checkpoints").exists()
    assert (tmp_path / "full" / "loss_curve.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("speed", [{"channels_last": True}, {"channels_last": True, "precision": "bf16"}])
def test_speed_settings_train_the_same_run_to_rounding_and_resume_bitwise(tmp_path, speed):
    """channels_last sums in another order: step 1's loss equals float32's to rounding; bf16 autocast to its
    8-bit mantissa. Either run trains (falling loss), resumes bitwise, and its network loads for float32
    inference with unit-norm embeddings."""
    base = train_embedding(SyntheticSource(), tiny_cfg(), SMALL_NET, tmp_path / "fp32", progress=False)
    cfg = tiny_cfg(**speed)
    w = train_embedding(SyntheticSource(), cfg, SMALL_NET, tmp_path / "fast", progress=False)
    log = json.loads((tmp_path / "fast" / "training_log.json").read_text())["loss"]
    ref = json.loads((base.parent / "training_log.json").read_text())["loss"]
    assert log[0] == pytest.approx(ref[0], rel=1e-2 if "precision" in speed else 1e-5)
    assert log != ref and np.mean(log[-2:]) < np.mean(log[:2])
    with pytest.raises(KeyboardInterrupt):
        train_embedding(SyntheticSource(crash_after=2 * 4), cfg, SMALL_NET, tmp_path / "resumed", progress=False)
    w_res = train_embedding(SyntheticSource(), cfg, SMALL_NET, tmp_path / "resumed", progress=False)
    a, b = (torch.load(p, weights_only=True)["state_dict"] for p in (w, w_res))
    assert all(torch.equal(a[k], b[k]) for k in a)
    with torch.no_grad():
        y = load_embedding_net(w)(torch.rand(1, 3, 24, 40))
    assert y.dtype == torch.float32 and torch.allclose(y.norm(dim=1), torch.ones(1, 24, 40), atol=1e-5)
    with pytest.raises(ValueError, match="precision"):
        tiny_cfg(precision="fp16")


@pytest.mark.parametrize("native", [False, True])
def test_precision_auto_trains_as_the_precision_the_device_runs_natively(tmp_path, monkeypatch, capfd, native):
    """'auto' is bf16 where the device runs bfloat16 natively and float32 elsewhere: the same weights and resume key
    as the explicit run (whose finished weights it reuses); explicit bf16 without native support warns, once."""
    monkeypatch.setattr(train_module, "native_bf16", lambda device: native)
    monkeypatch.setattr(train_module, "_WARNED", set())
    explicit = "bf16" if native else "fp32"
    w = train_embedding(SyntheticSource(), tiny_cfg(precision=explicit), SMALL_NET, tmp_path / "explicit",
                        progress=False)
    w_auto = train_embedding(SyntheticSource(), tiny_cfg(precision="auto"), SMALL_NET, tmp_path / "auto",
                             progress=False)
    a, b = (torch.load(p, weights_only=True) for p in (w, w_auto))
    assert a["key_hash"] == b["key_hash"] and all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])
    assert train_embedding(SyntheticSource(crash_after=0), tiny_cfg(precision="auto"), SMALL_NET, tmp_path / "explicit",
                           progress=False) == w
    assert json.loads((tmp_path / "auto" / "training_log.json").read_text())["config"]["train"]["precision"] == explicit
    assert "without native bfloat16" not in capfd.readouterr().err
    if not native:
        train_embedding(SyntheticSource(), tiny_cfg(precision="bf16", steps=2), SMALL_NET, tmp_path / "bf16",
                        progress=False)
        assert capfd.readouterr().err.count("precision bf16 on a cpu (torch capability") == 1


def test_a_network_trained_at_stride_16_segments_at_8_with_the_same_weights(tmp_path):
    """load_embedding_net(output_stride=8) rebuilds a stride-16 network at 8: layer3 undilated → dilation 2 without
    its stride, layer4 dilation 2 → 4, ASPP rates doubled, every weight as trained; unit embeddings of the frame's
    size. At the trained stride (or 0) it is the plain load; the method config takes 8, 16 or 0 only."""
    w = train_embedding(SyntheticSource(), tiny_cfg(steps=2), SMALL_NET, tmp_path, progress=False)
    plain, at16, at8 = (load_embedding_net(w, output_stride=s) for s in (0, 16, 8))
    assert at8.encoder.layer3[0].conv1.stride == (1, 1) and at8.encoder.layer3[0].conv1.dilation == (2, 2)
    assert at8.encoder.layer4[0].conv1.dilation == (4, 4) and plain.encoder.layer4[0].conv1.dilation == (2, 2)
    assert plain.encoder.layer3[0].conv1.stride == (2, 2)
    assert [b[0].dilation for b in at8.aspp.branches[1:]] == [(12, 12), (24, 24), (36, 36)]
    trained = torch.load(w, weights_only=True)["state_dict"]
    assert all(torch.equal(trained[k], v) for k, v in at8.state_dict().items())
    x = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        y0, y16, y8 = plain(x), at16(x), at8(x)
    assert torch.equal(y0, y16) and y8.shape == y0.shape and not torch.allclose(y8, y0)
    assert torch.allclose(y8.norm(dim=1), torch.ones(1, 48, 64), atol=1e-5)
    assert at_output_stride(NetConfig(output_stride=8), 16).aspp_rates == (3, 6, 9)
    sup = get_method_class("supervised")
    method = sup(sup.config_cls(net=SMALL_NET, test_output_stride=8, device="cpu"), workdir=tmp_path / "work")
    method.load(w)
    with torch.no_grad():
        assert torch.equal(method._net(x), y8)  # the method segments with the network rebuilt at 8
    with pytest.raises(ValueError, match="test_output_stride"):
        EmbeddingMethodConfig(test_output_stride=4)


def test_finished_run_is_reused_and_other_settings_refused(tmp_path):
    cfg = tiny_cfg(steps=2, checkpoint_every=1)
    w = train_embedding(SyntheticSource(), cfg, SMALL_NET, tmp_path, progress=False)
    assert train_embedding(SyntheticSource(crash_after=0), cfg, SMALL_NET, tmp_path, progress=False) == w
    assert train_embedding(SyntheticSource(crash_after=0), tiny_cfg(steps=2, checkpoint_every=2, device="cpu"),
                           SMALL_NET, tmp_path, progress=False) == w  # runtime-only settings don't matter
    with pytest.raises(ValueError, match="other settings"):
        train_embedding(SyntheticSource(), tiny_cfg(steps=2, lr=1e-2), SMALL_NET, tmp_path, progress=False)
    net = load_embedding_net(w)
    x = torch.rand(1, 3, 24, 40)
    with torch.no_grad():
        y = net(x)
    assert y.shape == (1, SMALL_NET.embed_dim, 24, 40)
    assert torch.allclose(y.norm(dim=1), torch.ones(1, 24, 40), atol=1e-5)


def test_network_shapes_and_config_errors():
    net = EmbeddingNet(NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8,
                                 output_stride=8, encoder="resnet34")).eval()
    with torch.no_grad():
        assert net(torch.rand(2, 3, 37, 53)).shape == (2, 16, 37, 53)
    with pytest.raises(ValueError, match="encoder"):
        NetConfig(encoder="vgg")
    with pytest.raises(ValueError, match="output_stride"):
        NetConfig(output_stride=32)
    with pytest.raises(ValueError, match="B×3×H×W"):
        net(torch.rand(3, 20, 20))


def test_segment_features_average_over_all_frames(analytic_dataset):
    video = Dataset(analytic_dataset).labeled("000000")
    torch.manual_seed(0)
    net = EmbeddingNet(SMALL_NET).eval()
    fids = video.frame_ids[:3]
    segmaps = {f: video.inst(f).astype(np.int64) - 1 for f in fids}  # objects 1, 2 → segments 0, 1
    feats, seen = segment_features(net, video, fids, segmaps, n_segments=3, batch_size=2)
    assert feats.shape == (3, 16) and seen.tolist() == [True, True, False]
    assert np.all(feats[2] == 0) and np.allclose(np.linalg.norm(feats[:2], axis=1), 1, atol=1e-5)
    emb = embed_frames(net, [video.rgb(f) for f in fids], "cpu").numpy()  # B×D×H×W
    for s in (0, 1):
        pix = np.concatenate([emb[i][:, segmaps[f] == s].T for i, f in enumerate(fids)])
        mean = pix.mean(0)
        assert np.allclose(feats[s], mean / np.linalg.norm(mean), atol=1e-5)
    small = embed_frames(net, [video.rgb(fids[0])], "cpu", image_size=80)  # run at half size, resized back
    assert small.shape == (1, 16, video.height, video.width)
    assert torch.allclose(small.norm(dim=1), torch.ones(1), atol=1e-5)
    segmaps[fids[0]][0, 0] = 3
    with pytest.raises(ValueError, match="outside"):
        segment_features(net, video, fids, segmaps, n_segments=3)


def mean_iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean over GT objects of the Hungarian-matched IoU (unmatched objects score 0)."""
    g_ids, p_ids = np.unique(gt[gt > 0]), np.unique(pred[pred > 0])
    iou = np.zeros((len(g_ids), len(p_ids)))
    for i, g in enumerate(g_ids):
        for j, p in enumerate(p_ids):
            inter = np.sum((gt == g) & (pred == p))
            iou[i, j] = inter / np.sum((gt == g) | (pred == p))
    r, c = linear_sum_assignment(-iou)
    return float(iou[r, c].sum() / len(g_ids))


@pytest.mark.slow
def test_supervised_method_fits_and_beats_one_segment(analytic_dataset, tmp_path):
    ds = Dataset(analytic_dataset)
    videos = [ds.labeled(v) for v in ds.video_ids]
    cls = get_method_class("supervised")
    cfg = EmbeddingMethodConfig(net=NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16),
                                train=TrainConfig.preset("tiny", steps=30, threads=2, image_size=96, crop=(48, 64)),
                                frame_stride=2,
                                cluster=MeanShiftConfig(min_component_px=20), device="cpu")
    method = cls(cfg, workdir=tmp_path)
    method.fit(videos)
    assert method.weights_path.is_file() and (method.weights_path.parent / "loss_curve.png").is_file()
    log = json.loads((method.weights_path.parent / "training_log.json").read_text())
    assert np.mean(log["loss"][-10:]) < 0.8 * np.mean(log["loss"][:10])
    # A training-video frame with three objects (a fit sanity check, not a generalisation claim).
    video, fid = videos[2], videos[2].frame_ids[-1]
    gt = video.inst(fid).astype(np.int64)
    fg = gt > 0
    assert len(np.unique(gt[fg])) >= 2
    pred = method.segment(video, fid, fg)
    assert pred.shape == gt.shape and np.all(pred[~fg] == 0)
    ours, one = mean_iou(np.where(fg, pred, 0), gt), mean_iou(fg.astype(np.int64), gt)
    assert ours > max(0.5, one + 0.2), (ours, one)


def test_v1_disjoint_trains_elsewhere_and_never_reads_test_labels(analytic_dataset, tmp_path):
    test_root = make_dataset(tmp_path / "test", two_box_scenes()[:1], n_frames=2, width=64, height=48, fx=60.0)
    test_ds = Dataset(test_root)
    cls = get_method_class("v1-disjoint")
    cfg = cls.config_cls(net=SMALL_NET, train=tiny_cfg(steps=2, image_size=64), train_data=str(analytic_dataset),
                         device="cpu")
    method = cls(cfg, workdir=tmp_path / "work")
    videos = [test_ds.video(v) for v in test_ds.video_ids]
    with ground_truth_forbidden(test_root):
        method.fit(videos)
        fg = np.ones((48, 64), bool)
        pred = method.segment(videos[0], videos[0].frame_ids[0], fg)
    assert pred.shape == (48, 64) and pred.max() >= 1
    log = json.loads((method.weights_path.parent / "training_log.json").read_text())
    assert log["steps"] == 2


def test_v1_disjoint_train_data_relative_to_the_working_directory(analytic_dataset, tmp_path, monkeypatch):
    """Through evaluate's sandbox (which refuses ground-truth names on relative paths) a relative train_data
    is opened by its absolute path: read as training data, not rejected as a cheat."""
    from selfseg.eval.cli import main as evaluate

    make_dataset(tmp_path / "train", two_box_scenes()[:1], n_frames=2, width=64, height=48, fx=60.0)
    monkeypatch.chdir(tmp_path)
    small = [f"net.{k}={v}" for k, v in vars(SMALL_NET).items() if k in ("width", "aspp_channels",
                                                                       "low_level_channels", "decoder_channels")]
    sets = ["train_data=train", "train.steps=2", "train.batch_size=2", "train.image_size=64", "train.crop=[32, 48]",
            "device=cpu", *small]
    assert evaluate(["--method", "v1-disjoint", "--data", str(analytic_dataset), "--folds", "0", "--out", "out",
                     "--quiet", *(a for s in sets for a in ("--set", s))]) == 0
    assert not (tmp_path / "out" / "rejected").exists()


def test_v1_disjoint_needs_its_training_data(tmp_path):
    cls = get_method_class("v1-disjoint")
    assert not cls.needs_ground_truth and cls.needs_fit
    with pytest.raises(DatasetError, match="train_data"):
        cls(workdir=tmp_path).fit([])
    with pytest.raises(DatasetError, match="not usable"):
        cls(cls.config_cls(train_data=str(tmp_path / "missing")), workdir=tmp_path).fit([])


def test_label_source_checks_label_maps(analytic_dataset):
    video = Dataset(analytic_dataset).video("000001")
    src = FrameLabelSource([(video, video.frame_ids[0], lambda v, f: np.zeros((3, 3), np.int32))])
    with pytest.raises(ValueError, match="label map"):
        src[0]
    with pytest.raises(ValueError, match="at least one"):
        FrameLabelSource([])


@pytest.mark.slow
def test_ours_masks_with_its_own_reconstructed_foreground(tmp_path):
    """`ours` with mask_background: φ1, its segment features and φ2 train on the recon stage's projected
    foreground masks (never ground truth, all under the guard); the masks are the stage's files."""
    from selfseg.config import load_config
    from selfseg.method.pipeline import Ours, OursConfig
    from selfseg.method.recon_stage import load_recon

    root = make_dataset(tmp_path / "dense", two_box_scenes()[:2], n_frames=20, width=160, height=120, arc_deg=30)
    ds = Dataset(root)
    fast = ["net.width=8", "net.aspp_channels=16", "net.decoder_channels=16", "net.low_level_channels=8",
            "pseudo.match.workers=1", "frame_stride=4", "feature_stride=4"]
    for phase in ("train", "phi1_train"):
        fast += [f"{phase}.steps=4", f"{phase}.batch_size=2", f"{phase}.crop=[64, 96]", f"{phase}.image_size=160",
                 f"{phase}.fg_crop=true", f"{phase}.mask_background=true"]
    method = Ours(load_config(OursConfig, overrides=fast), tmp_path / "work")
    train = [ds.video(v) for v in ds.video_ids]
    with ground_truth_forbidden(root):
        source, _ = method.label_source(train)
        cache = method.stage_cache(train)
        for i in range(0, len(source), 3):
            video, fid, _ = source.items[i]
            assert np.array_equal(source.foreground(i), load_recon(cache.path("recon", video.video_id)).fg_mask(fid))
        method.fit(train)
    fg_est = source.foreground(0)
    video, fid, _ = source.items[0]
    gt_fg = ds.labeled(video.video_id).inst(fid) > 0
    assert (fg_est & gt_fg).sum() > 0.8 * gt_fg.sum() and not np.array_equal(fg_est, gt_fg)  # close, not GT
