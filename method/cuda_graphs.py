"""CUDA graphs for fixed-shape inference: a function of tensors captured once per input shape, then replayed.

A single frame's network forward pass and mean-shift mode finding are a few hundred small GPU kernels each; launched
one by one from Python, their launch overhead, not the GPU, sets the frame rate. A captured graph launches them all
at once. Only CUDA tensors are graphed; on any other device the function is simply called, so the same code path runs
(and is tested) on the CPU. ``SELFSEG_CUDA_GRAPHS=0`` in the environment (or :data:`ENABLED` = False) turns graphs
off, e.g. to time without them.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from typing import Callable

import torch

ENABLED = os.environ.get("SELFSEG_CUDA_GRAPHS", "1") != "0"


class GraphedFunction:
    """``fn(*args)`` of tensors (or None) returning a tensor or a tuple of tensors (or None), replayed from a CUDA
    graph once an input signature (shapes, dtypes, device) has been called ``min_calls`` times.

    The function must be capturable: no host synchronisation (``.item()``, ``.any()`` in a condition, copies from
    host memory) and the same kernels on every call. Outputs are copies, so a later call never overwrites them. At
    most ``max_graphs`` graphs are kept (least recently used dropped with their memory).
    """

    def __init__(self, fn: Callable, min_calls: int = 2, max_graphs: int = 8):
        self.fn, self.min_calls, self.max_graphs = fn, min_calls, max_graphs
        self._graphs: OrderedDict = OrderedDict()
        self._calls: dict = {}

    def __call__(self, *args):
        first = next((a for a in args if a is not None), None)
        if not ENABLED or first is None or first.device.type != "cuda" or torch.is_grad_enabled():
            return self.fn(*args)
        key = tuple(None if a is None else (tuple(a.shape), a.dtype, a.device) for a in args)
        entry = self._graphs.get(key)
        if entry is None:
            self._calls[key] = self._calls.get(key, 0) + 1
            if self._calls[key] < self.min_calls:
                return self.fn(*args)
            entry = self._graphs[key] = self._capture(args)
            while len(self._graphs) > self.max_graphs:
                self._graphs.popitem(last=False)
        self._graphs.move_to_end(key)
        graph, static_in, static_out = entry
        for s, a in zip(static_in, args):
            if s is not None:
                s.copy_(a)
        graph.replay()
        if isinstance(static_out, tuple):
            return tuple(None if o is None else o.clone() for o in static_out)
        return static_out.clone()

    def _capture(self, args):
        """(graph, static inputs, static outputs) of ``fn`` on copies of ``args``, after warm-up calls on a side
        stream (as PyTorch's CUDA-graph recipe asks: lazy initialisation and autotuning happen outside capture)."""
        static_in = tuple(None if a is None else a.clone() for a in args)
        device = next(a for a in args if a is not None).device
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(2):
                self.fn(*static_in)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            static_out = self.fn(*static_in)
        return graph, static_in, static_out
