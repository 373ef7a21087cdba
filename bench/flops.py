"""FLOP counting, cold/warm timing and the in-process matmul reference shared by the benchmarks.

An MFU-style figure that needs no datasheet: a program's achieved FLOP/s (FLOPs from XLA's cost
analysis of the compiled program, with an analytic ViT count beside it as a cross-check) divided
by the FLOP/s of a plain matmul measured in the same process on the same device.
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.models.configs import decode_variant

#: Peak dense bf16 FLOP/s of known accelerators (vendor datasheets, without sparsity).
PEAK_BF16 = {"H100": 989e12, "H200": 989e12, "A100": 312e12}


def mfu_note(achieved: float) -> str:
    """``", MFU x% of peak bf16"`` for an accelerator of :data:`PEAK_BF16` (all local devices
    together), else "" (CPUs have no datasheet figure here: the matmul ratio stands)."""
    dev = jax.devices()[0]
    peak = next((p for k, p in PEAK_BF16.items() if k in dev.device_kind), None)
    if jax.default_backend() == "cpu" or peak is None:
        return ""
    return f", MFU {achieved / (peak * len(jax.devices())):.1%} of peak bf16"


def matmul_reference() -> tuple[bool, float]:
    """Prints the backend and the FLOP/s of the in-process matmul reference (bf16 8192^3 on an
    accelerator, float32 2048^3 on CPU); returns (on an accelerator, that FLOP/s)."""
    backend, dev = jax.default_backend(), jax.devices()[0]
    accel = backend != "cpu"
    print(f"backend {backend}, {len(jax.devices())} x {dev.device_kind}")
    dtype = jnp.bfloat16 if accel else jnp.float32
    ref = matmul_flops_per_s(dtype, 8192 if accel else 2048)
    print(f"reference: {np.dtype(dtype).name} matmul {ref / 1e9:.1f} GFLOP/s per process")
    return accel, ref


def vit_forward_flops(variant: str, n_tokens: int) -> float:
    """Analytic FLOPs of one ViT forward over ``n_tokens`` tokens.

    Per layer of width D and MLP width F: 4 N D^2 multiply-adds for the q, k, v and output
    projections, 2 N^2 D for the attention scores and values, 2 N D F for the MLP; FLOPs are
    twice the multiply-adds. Patch embedding, norms, heads and pooling are left out (a few
    percent).
    """
    arch = decode_variant(variant)
    d, depth, f = arch["width"], arch["depth"], arch["mlp_dim"]
    n = n_tokens
    return 2.0 * depth * (4 * n * d * d + 2 * n**2 * d + 2 * n * d * f)


def matmul_flops_per_s(dtype, n: int) -> float:
    """Warm FLOP/s of an n x n x n matmul on the default device (the in-process reference):
    the best of three timings of five products, which discounts other load on the machine."""
    a = jnp.asarray(np.random.default_rng(0).standard_normal((n, n)), dtype)
    f = jax.jit(lambda x, y: x @ y)
    f(a, a).block_until_ready()
    reps, best = 5, 0.0
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            out = f(a, a)
        out.block_until_ready()
        best = max(best, 2.0 * n**3 * reps / (time.perf_counter() - t0))
    return best


def cost_flops(compiled) -> float | None:
    """FLOPs of a compiled program from XLA's cost analysis (None where not implemented)."""
    try:
        cost = compiled.cost_analysis()
    except Exception:  # some backends do not implement it
        return None
    if isinstance(cost, (list, tuple)):
        cost = cost[0] if cost else None
    if not cost or "flops" not in cost:
        return None
    return float(cost["flops"])


def cold_and_warm(call, repeats: int) -> tuple[float, float]:
    """Seconds of the first ``call()`` (compilation included) and the median of ``repeats``
    more (warm)."""
    t0 = time.perf_counter()
    call()
    cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        warm.append(time.perf_counter() - t0)
    return cold, statistics.median(warm)
