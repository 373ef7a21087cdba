"""The standard detector that adapted 3PT-D is measured against (issue 38): Ultralytics
YOLOv8n trained from scratch (no pretrained weights) on a BOP dataset's images for a number
of minutes, then run on held-out BOP images, its detections written as a BOP 2D results JSON.

Runs in its own environment, never the package's (Ultralytics is AGPL-3.0; it is not a
dependency of threept_jax): ``python -m venv V && V/bin/pip install ultralytics``, then
``V/bin/python bench/yolo_reference.py --train D/train_pbr --val D/val_pbr --test T/val_pbr
--minutes 10 --out OUT``. ``bench/adapt_pace.py --yolo-python V/bin/python`` calls it and scores
``OUT/detections.json`` with the project's evaluator. Imports nothing of the project: it reads
the BOP files itself (boxes: ``scene_gt_info.json`` ``bbox_obj`` clipped to the image, as the
evaluator's ground truth; instances under 10 % visible left out, as BOP ignores them).

Settings are the issue's measurement: YOLOv8n from ``yolov8n.yaml`` (random init), image size
320, batch 16, the default augmentation (mosaic included), every core of the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import time


def _scenes(split: pathlib.Path):
    for scene in sorted(p for p in split.iterdir() if p.is_dir() and p.name.isdigit()):
        gt = json.loads((scene / "scene_gt.json").read_text())
        info = json.loads((scene / "scene_gt_info.json").read_text())
        for im in sorted(gt, key=int):
            rgb = next((scene / "rgb").glob(f"{int(im):06d}.*"))
            yield int(scene.name), int(im), rgb, gt[im], info[im]


def to_yolo(split: pathlib.Path, out: pathlib.Path, classes: list[int]) -> int:
    """BOP split -> ``out/images`` + ``out/labels`` (class cx cy w h, normalised)."""
    import cv2

    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    n = 0
    for sid, iid, rgb, gts, infos in _scenes(split):
        h, w = cv2.imread(str(rgb)).shape[:2]
        name = f"{sid:06d}_{iid:06d}"
        shutil.copy2(rgb, out / "images" / f"{name}{rgb.suffix}")
        lines = []
        for g, info in zip(gts, infos):
            if info.get("visib_fract", 1.0) < 0.1 or info.get("px_count_visib", 1) < 1:
                continue
            x, y, bw, bh = info["bbox_obj"]
            x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + bw, w), min(y + bh, h)
            if x1 <= x0 or y1 <= y0:
                continue
            lines.append(f"{classes.index(int(g['obj_id']))} {(x0 + x1) / 2 / w:.6f} "
                         f"{(y0 + y1) / 2 / h:.6f} {(x1 - x0) / w:.6f} {(y1 - y0) / h:.6f}")
        (out / "labels" / f"{name}.txt").write_text("\n".join(lines))
        n += 1
    return n


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", type=pathlib.Path, required=True, help="BOP split folder")
    p.add_argument("--val", type=pathlib.Path, required=True, help="BOP split folder")
    p.add_argument("--test", type=pathlib.Path, required=True, help="BOP split folder")
    p.add_argument("--minutes", type=float, required=True, help="training budget")
    p.add_argument("--out", type=pathlib.Path, required=True)
    p.add_argument("--imgsz", type=int, default=320)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    os.environ.setdefault("YOLO_OFFLINE", "1")
    from ultralytics import YOLO

    classes = sorted({int(g["obj_id"]) for split in (args.train, args.val)
                      for *_, gts, _ in _scenes(split) for g in gts})
    data = args.out / "yolo"
    counts = {name: to_yolo(split, data / name, classes)
              for name, split in (("train", args.train), ("val", args.val))}
    (data / "data.yaml").write_text(json.dumps({
        "path": str(data.resolve()), "train": "train/images", "val": "val/images",
        "names": {i: f"obj_{c:06d}" for i, c in enumerate(classes)}}))
    print(f"YOLO data: {counts} images, classes {classes}", flush=True)
    model = YOLO("yolov8n.yaml")  # the architecture only: random weights, nothing downloaded
    start = time.perf_counter()
    model.train(data=str(data / "data.yaml"), imgsz=args.imgsz, batch=args.batch,
                epochs=100_000, time=args.minutes / 60, device="cpu", workers=2,
                pretrained=False, amp=False, plots=False, project=str(args.out.resolve()),
                name="train", exist_ok=True, seed=args.seed, verbose=False, patience=0)
    train_s = time.perf_counter() - start
    detections = []
    for sid, iid, rgb, _, _ in _scenes(args.test):
        t0 = time.perf_counter()
        r = model.predict(str(rgb), imgsz=args.imgsz, conf=0.001, max_det=100, verbose=False,
                          device="cpu")[0]
        dt = time.perf_counter() - t0
        for (x0, y0, x1, y1), c, s in zip(r.boxes.xyxy.tolist(), r.boxes.cls.tolist(),
                                          r.boxes.conf.tolist()):
            detections.append({"scene_id": sid, "image_id": iid,
                               "category_id": classes[int(c)], "score": float(s),
                               "bbox": [x0, y0, x1 - x0, y1 - y0], "time": dt})
    (args.out / "detections.json").write_text(json.dumps(detections))
    (args.out / "yolo.json").write_text(json.dumps({"train_seconds": train_s,
                                                    "images": counts}))
    print(f"trained {train_s / 60:.1f} min; {len(detections)} detections on the test images",
          flush=True)


if __name__ == "__main__":
    main()
