"""How much one greedy decision's forward pass costs: the numba kernel (safelane.agents.inference), torch,
and a numpy ``@`` forward, one row and a batch of 64, measured side by side in one process.

    .venv/bin/python research/policy_forward.py

Prints JSON: median µs per call of each (single-threaded torch, as in training).
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch

from safelane.agents import inference
from safelane.agents.dqn import QNetwork


def median_us(call, repeats: int = 2000) -> float:
    """Median wall time of ``call()`` in µs over ``repeats`` calls (after a warm-up)."""
    for _ in range(100):
        call()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e6)


def numpy_forward(layers: inference.Layers, obs: np.ndarray) -> np.ndarray:
    """The same network with numpy's matrix products (BLAS; batch-size dependent rounding)."""
    x = obs
    for k, (w, b) in enumerate(layers):
        x = x @ w + b
        if k < len(layers) - 1:
            x = np.where(x > 0, x, np.expm1(x))
    return x


def measure(net: QNetwork, acting: inference.ActingNetwork, layers: inference.Layers, rows: int) -> dict:
    """Median µs of each forward pass on ``rows`` observations."""
    obs = np.random.default_rng(0).normal(size=(rows, 26)).astype(np.float32)
    obs_t = torch.from_numpy(obs)

    def torch_call() -> None:
        with torch.no_grad():
            net(obs_t).numpy()

    return {
        "numba_us": median_us(lambda: acting(obs)),
        "torch_us": median_us(torch_call),
        "numpy_us": median_us(lambda: numpy_forward(layers, obs)),
    }


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    net = QNetwork()
    acting = inference.ActingNetwork(net)
    layers = acting.layers()
    out = {}
    for rows in (1, 64):
        out[f"rows_{rows}"] = measure(net, acting, layers, rows)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
