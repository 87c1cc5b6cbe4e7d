"""Geometry beside RGB in the network's input (``NetConfig.geometry``): normals and depth channels checked on
analytic planes, their mirror and rotation under augmentation, the masked fill, and fit + segment end to end."""
import numpy as np
import pytest
import torch

from selfseg.config import ConfigError
from selfseg.dataset import Dataset
from selfseg.method.deploy import segment_frame
from selfseg.method.embed_method import EmbeddingMethodConfig
from selfseg.method.features import (DEPTH_UNIT_M, NORMAL_X, input_frame, mask_input, mirror, normals_cam,
                                     video_frame)
from selfseg.method.meanshift import MeanShiftConfig
from selfseg.method.network import RGB_MEAN, EmbeddingNet, NetConfig
from selfseg.method.train import FrameLabelSource, TrainConfig, _rotate, augment, train_embedding
from selfseg.registry import get_method_class

torch.set_num_threads(2)
K = np.array([[500.0, 0, 63.5], [0, 500.0, 47.5], [0, 0, 1]])
H, W = 96, 128


def plane_depth(normal, point, K=K, h=H, w=W) -> np.ndarray:
    """Depth (m) of the plane through ``point`` with ``normal`` (camera frame) at every pixel."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    return (np.dot(point, normal) / (rays @ normal)).astype(np.float32)


@pytest.mark.parametrize("tilt_deg", [0, 30, 60])
def test_normals_of_a_tilted_plane_face_the_camera(tilt_deg):
    t = np.radians(tilt_deg)
    n = np.array([np.sin(t), 0.0, -np.cos(t)])  # facing the camera (negative z), turned about the y axis
    got = normals_cam(plane_depth(n, np.array([0, 0, 0.7])), K)
    inner = got[3:-3, 3:-3]
    assert np.abs(inner - n).max() < 1e-3
    assert np.all(got[:2] == 0) and np.all(got[:, -2:] == 0)  # the stencil runs off the image: unknown


def test_normals_are_zero_without_depth_and_at_an_occlusion_edge():
    depth = plane_depth(np.array([0, 0, -1.0]), np.array([0, 0, 0.8]))
    depth[:, 64:] = 0.6  # a box face 20 cm in front, from column 64 on
    depth[40:50, 20:30] = 0  # a hole
    n = normals_cam(depth, K)
    assert np.all(n[:, 62:66] == 0)  # within NORMAL_STEP_PX of the 20 cm step
    assert np.all(n[38:52, 18:32][np.abs(n[38:52, 18:32]).sum(-1) > 0] @ [0, 0, 1] < -0.999)  # none but face-on
    assert np.all(n[40:50, 20:30] == 0) and np.all(n[38, 20:30] == 0)
    assert np.allclose(n[10:30, 10:60], [0, 0, -1], atol=1e-4) and np.allclose(n[10:30, 70:120], [0, 0, -1], atol=1e-4)


def test_the_depth_channel_is_the_depth_about_the_median():
    depth = np.full((H, W), 0.8, np.float32)
    depth[:, :40] = 0.7
    depth[:5] = 0
    f = input_frame(np.zeros((H, W, 3), np.uint8), depth, K, geometry=True)
    assert f.shape == (H, W, 7) and f.dtype == np.float32
    assert np.allclose(f[10, 50, 6], 0) and np.allclose(f[10, 10, 6], -0.1 / DEPTH_UNIT_M) and np.all(f[:5, :, 6] == 0)
    rgb = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    assert input_frame(rgb, depth, K) is rgb  # without geometry: the RGB frame itself


def test_a_mirrored_frame_is_the_frame_of_the_mirrored_scene():
    """Mirroring the input (test-time flip, training flip) must give what the camera would see of the mirrored
    scene: the image flipped and the normal's x negated."""
    n = np.array([0.4, -0.3, -0.866])
    n /= np.linalg.norm(n)
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    frame = input_frame(rgb, plane_depth(n, np.array([0.02, 0, 0.7])), K, True)
    Km = K.copy()
    Km[0, 2] = W - 1 - K[0, 2]
    n_m = n * [-1, 1, 1]
    seen = input_frame(rgb[:, ::-1].copy(), plane_depth(n_m, np.array([-0.02, 0, 0.7]), Km), Km, True)
    got = mirror(torch.from_numpy(frame).permute(2, 0, 1)[None])[0].permute(1, 2, 0).numpy()
    assert np.allclose(got[3:-3, 3:-3], seen[3:-3, 3:-3], atol=1e-3)
    assert np.allclose(seen[50, 60, 3:6], n_m, atol=1e-3) and np.allclose(frame[50, 60, 3:6], n, atol=1e-3)


def test_augment_mirrors_the_normals_with_the_image():
    n = np.array([0.5, 0.0, -0.866])
    frame = input_frame(np.full((H, W, 3), 128, np.uint8), plane_depth(n, np.array([0, 0, 0.7])), K, True)
    labels = np.zeros((H, W), np.int32)
    kw = dict(image_size=0, scale_range=(1.0, 1.0), crop=(64, 64), brightness=0, contrast=0, saturation=0, hue=0)
    xs = set()
    for seed in range(8):
        img, _ = augment(frame, labels, TrainConfig(flip=True, **kw), np.random.default_rng(seed))
        keep, _ = augment(frame, labels, TrainConfig(flip=False, **kw), np.random.default_rng(seed))
        x = float(np.median(img[NORMAL_X]))
        assert img.shape == (7, 64, 64) and np.isclose(abs(x), 0.5, atol=1e-3)
        want = keep if x > 0 else keep[:, :, ::-1] * np.array([1, 1, 1, -1, 1, 1, 1])[:, None, None]
        assert np.allclose(img[3:], want[3:])  # the geometry: as is, or mirrored with the normal's x negated
        xs.add(round(x, 2))
    assert xs == {0.5, -0.5}  # flipped in some draws, not in others
    kw.update(image_size=100, scale_range=(0.8, 1.2))  # resized by area (OpenCV takes 4 channels at most there)
    img, _ = augment(frame, labels, TrainConfig(flip=False, **kw), np.random.default_rng(0))
    assert np.allclose(img[3:6, 10:-10, 10:-10], np.array(n, np.float32)[:, None, None], atol=1e-3)


def test_rotation_turns_the_normals_with_the_image():
    """A +90° turn of the image (counter-clockwise as displayed, y down) carries the image's +x direction to −y."""
    n = np.array([0.5, 0.0, -0.866])
    frame = input_frame(np.zeros((H, H, 3), np.uint8), plane_depth(n, np.array([0, 0, 0.7]), h=H, w=H), K, True)
    img, _, _ = _rotate(frame, np.zeros((H, H), np.int32), np.ones((H, H), bool), 90.0)
    assert img.shape == (H, H, 7)
    assert np.allclose(img[H // 2, H // 2, 3:6], [0.0, -0.5, -0.866], atol=1e-3)


def test_masked_pixels_get_the_rgb_mean_and_no_geometry():
    x = torch.rand(1, 7, 8, 8)
    fg = np.zeros((8, 8), bool)
    fg[2:6, 2:6] = True
    out = mask_input(x, [fg])
    assert torch.equal(out[0, :, 2:6, 2:6], x[0, :, 2:6, 2:6])
    assert torch.allclose(out[0, :3, 0, 0], torch.tensor(RGB_MEAN)) and torch.all(out[0, 3:, 0, 0] == 0)


def test_the_network_and_the_trainer_refuse_the_wrong_input():
    assert NetConfig().in_channels == 3 and NetConfig(geometry=True).in_channels == 7
    net = EmbeddingNet(NetConfig(geometry=True, width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8))
    assert net(torch.rand(1, 7, 32, 32)).shape == (1, 16, 32, 32)
    with pytest.raises(ValueError, match="B×7×H×W"):
        net(torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match="B×3×H×W"):
        EmbeddingNet(NetConfig(width=8))(torch.rand(1, 7, 32, 32))

    class RGBSource:  # RGB frames: no ``geometry`` attribute
        def __len__(self):
            return 1

        def __getitem__(self, i):
            return np.zeros((32, 32, 3), np.uint8), np.zeros((32, 32), np.int32)

    with pytest.raises(ValueError, match="build the source with geometry=True"):
        train_embedding(RGBSource(), TrainConfig.preset("tiny"), NetConfig(geometry=True), "unused")


def test_supervised_with_geometry_fits_and_segments_from_depth(analytic_dataset, tmp_path):
    """fit and segment through the geometry path: the training source carries the channels, and segmenting reads
    the frame's depth (a frame with no depth embeds otherwise)."""
    ds = Dataset(analytic_dataset)
    videos = [ds.labeled(v) for v in ds.video_ids]
    cfg = EmbeddingMethodConfig(net=NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16,
                                              geometry=True),
                                frame_stride=2, device="cpu", cluster=MeanShiftConfig(min_component_px=20),
                                train=TrainConfig.preset("tiny", steps=10, threads=2, image_size=96, crop=(48, 64),
                                                         mask_background=True, fg_crop=True))
    m = get_method_class("supervised")(cfg, workdir=tmp_path)
    m.fit(videos)
    video, fid = videos[2], videos[2].frame_ids[-1]
    fg = video.inst(fid) > 0
    frame = video_frame(video, fid, True)
    has_normal = np.linalg.norm(frame[fg][:, 3:6], axis=-1)
    assert frame.shape[2] == 7 and np.mean(np.isclose(has_normal, 1, atol=1e-4)) > 0.7  # none within 2 px of an outline
    pred = m.segment(video, fid, fg)
    assert pred.shape == fg.shape and np.all(pred[~fg] == 0) and np.all(pred[fg] > 0)
    assert np.array_equal(segment_frame(m, video.rgb(fid), fg, video.depth_m(fid), video.K(fid)), pred)
    flat = input_frame(video.rgb(fid), np.zeros_like(video.depth_m(fid)) + 0.7, video.K(fid), True)
    assert not np.allclose(m.embed(flat, fg), m.embed(frame, fg), atol=1e-3)
    with pytest.raises(ConfigError, match="pass --depth and --intrinsics"):
        segment_frame(m, video.rgb(fid), fg)
