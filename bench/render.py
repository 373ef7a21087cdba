"""Benchmark: renders/s of the JAX rasterizer against Mitsuba 3 (same process, same views).

A ~2000-face mesh (T-LESS obj 4 from ../shared/meshes/bop, decimated to 1000 faces and
subdivided so no edge exceeds 0.1 x diameter; a procedural torus when the shared meshes are
absent) is rendered at random rotations, the object filling ~80 % of the image, with the
outputs depth, mask, xyz and normal, by:

* ``jax``: :func:`threept_jax.render.raster.render` (jit, one call per batch);
* ``mitsuba``: :class:`threept_jax.render.mitsuba_backend.MitsubaRenderer` (``llvm_ad_rgb`` on
  CPU, ``cuda_ad_rgb`` on a GPU; one ray-cast kernel per batch).

Rows: 128x128 and 512x512 in batches of 64, and 5140 templates (the detector's
super-Fibonacci grid) at 128x128 end to end: poses to renders on the device, in batches of 64,
compilation included. Then the rasterizer's program with its compile options
(``raster.RASTER_COMPILE_OPTIONS``) against XLA's default, at 128x128 and 640x480: compile
seconds and warm calls, ratio ours / default. Cold = first call (compilation included), warm =
median of ``--reps`` calls, alternating between the backends so that both see the same load
(the machine may be shared).

    python bench/render.py [--reps 5] [--batch 64] [--skip-templates]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from threept_jax.geometry.grids import super_fibonacci_rotations  # noqa: E402
from threept_jax.geometry.rotations import random_rotations  # noqa: E402
from threept_jax.render import raster  # noqa: E402
from threept_jax.render.mesh import Mesh, load_mesh, prepare_mesh, to_raster_mesh  # noqa: E402
from threept_jax.render.mitsuba_backend import MitsubaRenderer  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes" / "bop"
OUTPUTS = ("depth", "mask", "xyz", "normal")


def bench_mesh() -> Mesh:
    path = SHARED / "tless" / "models" / "obj_000004.ply"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if path.is_file():
            mesh = load_mesh(path)
        else:
            import trimesh

            t = trimesh.creation.torus(major_radius=40.0, minor_radius=15.0)
            mesh = Mesh(vertices=t.vertices, faces=t.faces, name="torus")
        return prepare_mesh(mesh, max_faces=1000, max_edge_fraction=0.1)


def views(mesh: Mesh, R: np.ndarray, hw: tuple[int, int]):
    """T_cam_obj [B, 4, 4] at rotations R with the object centred, K [3, 3] with the bounding
    sphere filling 80 % of the image width."""
    H, W = hw
    z = 4.0 * mesh.diameter
    f = 0.8 * W * z / mesh.diameter
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], np.float32)
    T = np.tile(np.eye(4, dtype=np.float32), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = -np.einsum("bij,j->bi", R, mesh.center) + [0, 0, z]
    return T, K


def timed_pair(fa, fb, reps):
    """Cold time of each, then ``reps`` alternating warm runs (so both see the same machine
    load); returns (cold_a, warm_a, cold_b, warm_b), warm = median seconds."""
    cold = []
    for f in (fa, fb):
        t0 = time.perf_counter()
        f()
        cold.append(time.perf_counter() - t0)
    warm = ([], [])
    for _ in range(reps):
        for k, f in enumerate((fa, fb)):
            t0 = time.perf_counter()
            f()
            warm[k].append(time.perf_counter() - t0)
    return cold[0], float(np.median(warm[0])), cold[1], float(np.median(warm[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--reps", type=int, default=9)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--skip-templates", action="store_true")
    args = ap.parse_args()

    mesh = bench_mesh()
    rmesh = to_raster_mesh(mesh)
    mit = MitsubaRenderer(mesh)
    B = args.batch
    R = np.asarray(random_rotations(jax.random.key(0), (B,)))
    print(f"device: jax {jax.devices()[0].platform}, mitsuba {mit.mi.variant()}; mesh "
          f"{mesh.name} {mesh.num_faces} faces (padded {rmesh.num_faces_padded}), "
          f"cull_backfaces={bool(rmesh.cull_backfaces)}; outputs {','.join(OUTPUTS)}")
    rows = []
    for hw in ((128, 128), (512, 512)):
        T, K = views(mesh, R, hw)
        Tj, Kj = jnp.asarray(T), jnp.asarray(K)
        jcold, jwarm, mcold, mwarm = timed_pair(
            lambda Tj=Tj, Kj=Kj, hw=hw: jax.block_until_ready(
                raster.render(rmesh, Tj, Kj, hw, OUTPUTS)),
            lambda T=T, K=K, hw=hw: mit.render(T, K, hw, OUTPUTS),
            args.reps,
        )
        rows.append((f"{hw[0]}x{hw[1]} batch {B}", B / jwarm, B / mwarm, jcold, mcold))

    if not args.skip_templates:
        Rt = super_fibonacci_rotations(5140)
        n = len(Rt)
        pad = (-n) % B
        Rt = np.concatenate([Rt, np.repeat(Rt[:1], pad, 0)])
        hw = (128, 128)

        def all_templates(render_batch):
            t0 = time.perf_counter()
            for s in range(0, len(Rt), B):
                render_batch(*views(mesh, Rt[s : s + B], hw))
            return time.perf_counter() - t0

        # Templates feed the detector's image encoder, a JAX model: both backends end with the
        # renders as device arrays.
        def jax_batch(T, K):
            return jax.block_until_ready(
                raster.render(rmesh, jnp.asarray(T), jnp.asarray(K), hw, OUTPUTS)
            )

        def mitsuba_batch(T, K):
            return jax.block_until_ready(jax.device_put(mit.render(T, K, hw, OUTPUTS)))

        jtot = all_templates(jax_batch)
        mtot = all_templates(mitsuba_batch)
        rows.append(("5140 templates 128x128 (s)", jtot, mtot, None, None))

    print(f"{'config':28s} {'jax r/s':>10s} {'mitsuba r/s':>12s} {'jax/mitsuba':>12s}"
          f" {'jax cold s':>11s} {'mitsuba cold s':>15s}")
    for name, j, m, jc, mc in rows:
        if jc is None:  # end-to-end seconds: ratio is speed-up
            print(f"{name:28s} {j:10.2f} {m:12.2f} {m / j:12.2f} {'':>11s} {'':>15s}")
        else:
            print(f"{name:28s} {j:10.0f} {m:12.0f} {j / m:12.2f} {jc:11.2f} {mc:15.2f}")
    compile_options(rmesh, mesh, R, args.reps)


def compile_options(rmesh, mesh, R, reps):
    """The rasterizer's program compiled with its options (``raster.RASTER_COMPILE_OPTIONS``:
    XLA:CPU's loop emitters) against XLA's default (the fusion emitters), the same inputs in
    this process: compile seconds, then warm calls alternating."""
    print("rasterizer compile options (ours = RASTER_COMPILE_OPTIONS, reference = XLA default)")
    for hw, B in (((128, 128), len(R)), ((480, 640), 4)):
        T, K = views(mesh, R[:B], hw)
        K = np.broadcast_to(K, (B, 3, 3))  # the program's own layout: one K per view
        args = (rmesh, jnp.asarray(T), jnp.asarray(K), jnp.float32(1.0), jnp.float32(0.3),
                jnp.float32(0.02), jnp.float32(45.0))
        lowered = raster._render_jit.lower(*args, hw=hw, outputs=OUTPUTS,
                                           tile=raster.default_tile(hw), chunk=None)
        compiled, seconds = [], []
        for options in (raster.RASTER_COMPILE_OPTIONS, {"xla_cpu_use_fusion_emitters": True}):
            t0 = time.perf_counter()
            compiled.append(lowered.compile(compiler_options=options))
            seconds.append(time.perf_counter() - t0)
        _, ours, _, ref = timed_pair(*(lambda c=c, a=args: jax.block_until_ready(c(*a))
                                       for c in compiled), reps)
        print(f"  {hw[1]}x{hw[0]} x {B} views: compile {seconds[0]:.2f} s vs {seconds[1]:.2f} s "
              f"({seconds[0] / seconds[1]:.2f}x), warm {ours * 1e3:.1f} ms vs {ref * 1e3:.1f} ms "
              f"({ours / ref:.2f}x)")


if __name__ == "__main__":
    main()
