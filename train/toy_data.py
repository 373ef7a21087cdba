"""A small records folder without a renderer: flat textured "cards" pasted on backgrounds.

For the training system's tests and a CPU smoke run of ``train/launch.py`` before the data
generator has produced real data. Each object is a 2-D sprite (a disc or a rounded square with
a stripe and a dot, so its in-plane rotation shows; one object is a ring pattern with a
continuous symmetry about z). An instance at R_cam_obj is the sprite turned by R's in-plane
angle atan2(R[1, 0], R[0, 0]) and scaled to the projected size f * diameter / z of a card of
the object's diameter at depth z; boxes, visible masks, visib_fract and T_cam_obj are exact
for that image. Bank renders use the same sprite turned by each render rotation's in-plane
angle, with the bounding disc spanning ``banks.FILL`` of the image. The out-of-plane part of
the rotations is not rendered: this data checks formats and plumbing, not learning.

Writes ``<out>/{train,val}/*.array_record``, ``<out>/objects.json`` and ``<out>/banks/``.
``python -m train.toy_data --out DIR`` writes one.
"""

from __future__ import annotations

import argparse
import pathlib

import cv2
import numpy as np
from array_record.python.array_record_module import ArrayRecordWriter

from threept_jax.data import banks, records
from threept_jax.geometry.symmetry import ContinuousSymmetry, Symmetries
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations

SPRITE = 64


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def make_sprite(rng: np.random.Generator, kind: str) -> np.ndarray:
    """uint8 [64, 64, 4] RGBA sprite of an object; its bounding disc is the whole sprite."""
    s = SPRITE
    yy, xx = np.mgrid[:s, :s].astype(np.float32)
    r = np.hypot(xx - (s - 1) / 2, yy - (s - 1) / 2)
    colors = rng.integers(30, 226, (3, 3))
    rgb = np.empty((s, s, 3), np.uint8)
    rgb[:] = colors[0]
    if kind == "rings":
        rgb[(r // 6).astype(int) % 2 == 1] = colors[1]
        alpha = r <= s / 2 - 1
    else:
        rgb[(xx > s * 0.55) & (xx < s * 0.75)] = colors[1]
        rgb[np.hypot(xx - s * 0.3, yy - s * 0.3) < s * 0.1] = colors[2]
        if kind == "disc":
            alpha = r <= s / 2 - 1
        else:  # a square inscribed in the bounding disc
            half = (s / 2 - 1) / np.sqrt(2)
            alpha = (np.abs(xx - (s - 1) / 2) <= half) & (np.abs(yy - (s - 1) / 2) <= half)
    return np.concatenate([rgb, (alpha * 255).astype(np.uint8)[..., None]], -1)


def _in_plane_angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))


def _place(sprite: np.ndarray, angle_deg: float, size: float, centre_uv, out_hw) -> np.ndarray:
    """The sprite turned by ``angle_deg``, scaled so its 64 px become ``size`` px and centred at
    pixel-centre ``centre_uv``, on an ``out_hw`` canvas (RGBA float32, alpha in [0, 1])."""
    s = SPRITE
    A = cv2.getRotationMatrix2D(((s - 1) / 2, (s - 1) / 2), -angle_deg, size / s)
    A[:, 2] += np.asarray(centre_uv, np.float64) - (s - 1) / 2
    out = cv2.warpAffine(sprite.astype(np.float32), A, (out_hw[1], out_hw[0]),
                         flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out[..., 3] /= 255.0
    return out


def render_bank(obj_id: int, sprite: np.ndarray, diameter: float, symmetries: Symmetries,
                render_size: int, num_templates: int) -> banks.RenderBank:
    """A bank of the sprite at the prior and template rotations (module docstring)."""
    def render(R):
        size = banks.FILL * render_size
        c = (render_size - 1) / 2
        im = _place(sprite, _in_plane_angle(R), size, (c, c), (render_size, render_size))
        rgb = im[..., :3] * im[..., 3:] + 255.0 * (1 - im[..., 3:])  # white background
        return np.clip(np.round(rgb), 0, 255).astype(np.uint8)

    prior_R = prior_view_rotations()
    tmpl_R = super_fibonacci_rotations(num_templates)
    return banks.RenderBank(
        obj_id=obj_id, prior_rgb=np.stack([render(R) for R in prior_R]), prior_rotations=prior_R,
        template_rgb=np.stack([render(R) for R in tmpl_R]), template_rotations=tmpl_R,
        symmetries=banks.bank_symmetries(symmetries), diameter=diameter,
        center=np.zeros(3), radius=diameter / 2)


def make_image(rng: np.random.Generator, objects: dict, image_hw, scene_id: int, im_id: int,
               max_instances: int = 4) -> dict:
    """One annotated image (records format) with 1..max_instances pasted objects."""
    h, w = image_hw
    f = 1.2 * w
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], np.float64)
    grad = np.linspace(0, 1, w)[None, :, None] * rng.uniform(-60, 60, 3)
    img = rng.uniform(60, 190, 3) + grad + rng.normal(0, 12, (h, w, 3))
    ids = list(objects)
    n = int(rng.integers(1, max_instances + 1))
    pad = 64  # the amodal silhouette is drawn on a larger canvas, as BOP's bbox_obj allows
    instances = np.zeros((h, w), np.uint16)
    full_masks, poses, obj_ids = [], [], []
    for i in range(n):
        obj = int(rng.choice(ids))
        sprite, diameter = objects[obj]
        size = float(rng.uniform(0.18, 0.45) * min(h, w))
        uv = rng.uniform([0.1 * w, 0.1 * h], [0.9 * w, 0.9 * h])
        R = _random_rotations(rng, 1)[0]
        z = f * diameter / size
        t = np.linalg.inv(K) @ np.array([uv[0], uv[1], 1.0]) * z
        placed = _place(sprite, _in_plane_angle(R), size, uv + pad, (h + 2 * pad, w + 2 * pad))
        alpha = placed[pad:pad + h, pad:pad + w, 3:]
        img = placed[pad:pad + h, pad:pad + w, :3] * alpha + img * (1 - alpha)
        full = placed[..., 3] > 0.5
        instances[alpha[..., 0] > 0.5] = i + 1  # later instances occlude earlier ones
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        full_masks.append(full)
        poses.append(T)
        obj_ids.append(obj)
    bbox_obj, bbox_visib, visib = [], [], []
    for i, full in enumerate(full_masks):
        ys, xs = np.nonzero(full)
        bbox_obj.append([xs.min() - pad, ys.min() - pad, xs.max() + 1 - pad, ys.max() + 1 - pad])
        vis = instances == i + 1
        if vis.any():
            vy, vx = np.nonzero(vis)
            bbox_visib.append([vx.min(), vy.min(), vx.max() + 1, vy.max() + 1])
        else:
            bbox_visib.append([0, 0, 0, 0])
        visib.append(vis.sum() / full.sum())
    return {
        "rgb": np.clip(np.round(img), 0, 255).astype(np.uint8),
        "instances": instances,
        "K": K.astype(np.float32),
        "T_cam_world": np.eye(4, dtype=np.float32),
        "obj_id": np.asarray(obj_ids, np.int32),
        "T_cam_obj": np.asarray(poses, np.float32),
        "bbox_obj": np.asarray(bbox_obj, np.float32),
        "bbox_visib": np.asarray(bbox_visib, np.float32),
        "visib_fract": np.asarray(visib, np.float32),
        "scene_id": np.int32(scene_id),
        "im_id": np.int32(im_id),
        "source": "toy",
    }


def write_toy_records(out_dir, *, num_objects: int = 6, num_val_objects: int = 2,
                      num_train: int = 24, num_val: int = 8, image_hw=(96, 128),
                      render_size: int = 32, num_templates: int = 32, train_shards: int = 2,
                      seed: int = 0) -> pathlib.Path:
    """Write a toy records folder (module docstring); returns its path.

    Objects ``1..num_objects``; the last ``num_val_objects`` appear only in the val split
    (meshes training never sees). Object 1 is the ring pattern with a continuous symmetry.
    """
    if not 0 < num_val_objects < num_objects:
        raise ValueError("need 0 < num_val_objects < num_objects")
    out = pathlib.Path(out_dir)
    rng = np.random.default_rng(seed)
    entries, sprites = [], {}
    for obj_id in range(1, num_objects + 1):
        kind = "rings" if obj_id == 1 else ("disc" if obj_id % 2 else "square")
        sym = (Symmetries(continuous=(ContinuousSymmetry(np.array([0.0, 0, 1]), np.zeros(3)),))
               if kind == "rings" else Symmetries())
        diameter = float(rng.uniform(60, 200))
        sprite = make_sprite(rng, kind)
        bank = render_bank(obj_id, sprite, diameter, sym, render_size, num_templates)
        path = out / "banks" / f"obj_{obj_id:06d}.npz"
        banks.save_bank(path, bank)
        split = "val" if obj_id > num_objects - num_val_objects else "train"
        entries.append(banks.ObjectEntry(obj_id, f"toy_{kind}_{obj_id}", diameter, sym, path,
                                         split))
        sprites[obj_id] = (sprite, diameter)
    banks.write_object_table(out, entries)
    for split, count, shards in (("train", num_train, train_shards), ("val", num_val, 1)):
        objs = {e.obj_id: sprites[e.obj_id] for e in entries if e.split == split}
        examples = [records.encode_example(make_image(rng, objs, image_hw, 0, i))
                    for i in range(count)]
        (out / split).mkdir(parents=True, exist_ok=True)
        for s in range(shards):
            writer = ArrayRecordWriter(
                str(out / split / f"toy-{s:05d}-of-{shards:05d}.array_record"), "group_size:1")
            for ex in examples[s::shards]:
                writer.write(ex)
            writer.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="records folder to write")
    parser.add_argument("--num-train", type=int, default=64)
    parser.add_argument("--num-val", type=int, default=16)
    parser.add_argument("--image-size", type=int, nargs=2, default=(192, 256),
                        metavar=("H", "W"))
    parser.add_argument("--render-size", type=int, default=32)
    parser.add_argument("--num-templates", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    path = write_toy_records(args.out, num_train=args.num_train, num_val=args.num_val,
                             image_hw=tuple(args.image_size), render_size=args.render_size,
                             num_templates=args.num_templates, seed=args.seed)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
