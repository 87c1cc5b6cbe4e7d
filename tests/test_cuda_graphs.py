"""CUDA graphs of fixed-shape inference (``selfseg.method.cuda_graphs``): replaying a captured graph gives what the
plain call gives, outputs are never overwritten by a later replay, graphs follow the input shapes and the net's
weights. On the CPU the plain call runs and nothing is captured; the CUDA cases run where a GPU is present."""
import numpy as np
import pytest
import torch

from selfseg.method import cuda_graphs
from selfseg.method.cuda_graphs import GraphedFunction
from selfseg.method.features import embed_frames, foreground_box, graphed_forward
from selfseg.method.network import EmbeddingNet, NetConfig

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU"))]
SMALL_NET = NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16)


def fn(a, b):
    """A few dozen kernels, with a None input passed through and an output that aliases nothing."""
    out = a
    for _ in range(20):
        out = torch.tanh(out @ a.T @ a * 0.1 + 1.0)
    return out.sum(-1), None if b is None else out + b


@pytest.mark.parametrize("device", DEVICES)
def test_replay_equals_the_plain_call(device):
    g = GraphedFunction(fn, min_calls=2, max_graphs=2)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        shapes = [(5, 4), (5, 4), (5, 4), (7, 4), (7, 4), (9, 4), (9, 4), (5, 4)]
        outputs = []
        for shape in shapes:
            a, b = (torch.randn(shape, generator=gen).to(device) for _ in range(2))
            got = g(a, b if shape[0] != 9 else None)
            want = fn(a, b if shape[0] != 9 else None)
            torch.testing.assert_close(got[0], want[0], rtol=1e-5, atol=1e-6)
            assert (got[1] is None) == (want[1] is None)
            outputs.append((got[0].clone(), got[0]))
    for kept, returned in outputs:  # later replays did not overwrite earlier outputs
        assert torch.equal(kept, returned)
    if device == "cuda":  # captured on each shape's second call; at most two graphs kept, least recently used out
        assert [k[0][0] for k in g._graphs] == [(9, 4), (5, 4)]
    else:
        assert not g._graphs
    with torch.enable_grad():  # with gradients on, never a graph
        a = torch.randn(3, 4, device=device, requires_grad=True)
        g(a, None)[0].sum().backward()
        assert a.grad is not None


@pytest.mark.parametrize("device", DEVICES)
def test_graphed_network_embeds_as_the_eager_network(device):
    """``embed_frames`` of whole frames (graphed on CUDA from the second frame on) against the network run with
    graphs turned off; weights changed in place are read by the replay, a moved net gets a new graph."""
    torch.manual_seed(0)
    net = EmbeddingNet(SMALL_NET).to(device).eval()
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (60, 80, 3), dtype=np.uint8) for _ in range(4)]

    def eager(rgbs):
        cuda_graphs.ENABLED = False
        try:
            return embed_frames(net, rgbs, device, 48)
        finally:
            cuda_graphs.ENABLED = True

    for f in frames:
        torch.testing.assert_close(embed_frames(net, [f], device, 48), eager([f]), rtol=1e-4, atol=1e-5)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(1.5)
    torch.testing.assert_close(embed_frames(net, frames[:1], device, 48), eager(frames[:1]), rtol=1e-4, atol=1e-5)
    graphs = net.__dict__["_cuda_graphs"]
    assert len(graphs) == 1 and len(next(iter(graphs.values()))._graphs) == (1 if device == "cuda" else 0)
    key = next(iter(graphs))
    net.to(torch.float64).to(torch.float32)  # new weight tensors: the old graph must not be replayed
    torch.testing.assert_close(embed_frames(net, frames[:1], device, 48), eager(frames[:1]), rtol=1e-4, atol=1e-5)
    assert graphed_forward(net) is not None and key not in net.__dict__["_cuda_graphs"]


@pytest.mark.parametrize("device", DEVICES)
def test_square_crops_replay_one_graph_as_the_eager_network_embeds(device):
    """Foreground boxes of four shapes, grown to squares: one input shape, so on CUDA one graph (captured on its
    second call) serves every frame, and it embeds as the network with graphs off."""
    torch.manual_seed(0)
    net = EmbeddingNet(SMALL_NET).to(device).eval()
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (60, 80, 3), dtype=np.uint8) for _ in range(4)]
    masks = []
    for y0, y1, x0, x1 in ((5, 20, 10, 70), (10, 55, 30, 50), (40, 60, 0, 80), (20, 40, 20, 40)):
        m = np.zeros((60, 80), bool)
        m[y0:y1, x0:x1] = True
        masks.append(m)
    boxes = [foreground_box(m, 0.1) for m in masks]

    def embed(i, graphs=True):
        cuda_graphs.ENABLED = graphs
        try:
            return embed_frames(net, frames[i:i + 1], device, 48, boxes[i:i + 1], masks[i:i + 1], square=True)
        finally:
            cuda_graphs.ENABLED = True

    for i in range(4):
        torch.testing.assert_close(embed(i), embed(i, graphs=False), rtol=1e-4, atol=1e-5)
    graphs = next(iter(net.__dict__["_cuda_graphs"].values()))._graphs
    assert len(graphs) == (1 if device == "cuda" else 0)
