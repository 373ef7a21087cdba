"""BOP datasets in and out: lazy reader, typed records, result files and a scene writer.

The layout and field names follow the BOP toolkit's `docs/bop_datasets_format.md`
(BOP-scenewise format) and its `bop_toolkit_lib/inout.py`:

```
DATASET/
  camera[_SENSOR].json            optional: width, height, fx, fy, cx, cy, depth_scale
  test_targets_bop19.json         [{scene_id, im_id, obj_id, inst_count}]  (6D localisation)
  test_targets_bop24.json         [{scene_id, im_id}]                      (6D/2D detection)
  test_targets_multiview_bop25.json  multi-view groups (see `load_multiview_targets`)
  models[_eval]/models_info.json, obj_{obj_id:06d}.ply (+ texture png)
  {split}/{scene_id:06d}/
    scene_camera[_SENSOR].json    per image: cam_K (row-major), depth_scale, cam_R_w2c, cam_t_w2c
    scene_gt[_SENSOR].json        per image: [{obj_id, cam_R_m2c, cam_t_m2c}]  (mm)
    scene_gt_info[_SENSOR].json   per image: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]
    rgb|gray[_SENSOR]/{im_id:06d}.png|jpg|tif, depth[_SENSOR]/, mask[_SENSOR]/, mask_visib[_SENSOR]/
```

Conventions: poses are ``T_cam_obj`` (4x4 float64, translation in mm) built from
``cam_R_m2c``/``cam_t_m2c``; world extrinsics, when present, are ``T_cam_world`` from
``cam_R_w2c``/``cam_t_w2c``. Opening a dataset reads no image and no per-scene JSON: scenes
load their JSON on first use and images are read one at a time on request.

Writers produce files the official toolkit reads: the 6D results CSV
(`inout.save_bop_results`: ``scene_id,im_id,obj_id,score,R,t,time``, R row-major, t in mm,
one time per image), the 2D results JSON (`inout.save_coco_results`: amodal ``bbox`` [x, y,
w, h], visible-mask COCO RLE, integer ids) and whole scenes (`BopSceneWriter`), whose
``scene_gt_info`` fields are computed as in `scripts/calc_gt_info.py` (``bbox_obj`` from the
full silhouette, ``[x, y, x_max - x_min, y_max - y_min]``, [-1]*4 when nothing is visible).
JSON is formatted like `inout.save_json` (one top-level entry per line, integer keys in
numeric order) and written atomically (temporary file + rename).

The package: :mod:`.types` (records), :mod:`.json_format`, :mod:`.models`
(``models_info.json``, targets), :mod:`.reader` (``BopDataset``), :mod:`.results` (6D CSV, 2D JSON,
RLE) and :mod:`.writer` (``BopSceneWriter``).
"""

from threept_jax.data.bop.json_format import (
    write_json_atomic,
)
from threept_jax.data.bop.models import (
    CELL_FILE,
    MULTIVIEW_TARGETS_FILE,
    compute_model_info,
    load_cell,
    load_models,
    load_models_info,
    load_multiview_targets,
    load_targets,
    write_cell,
    write_models_info,
    write_multiview_targets,
    write_targets,
)
from threept_jax.data.bop.reader import (
    BopDataset,
    BopScene,
    BopSplit,
)
from threept_jax.data.bop.results import (
    check_consistent_times,
    mask_to_rle,
    read_detection_results,
    read_pose_results,
    rle_to_mask,
    top_estimates_per_image,
    write_detection_results,
    write_pose_results,
)
from threept_jax.data.bop.types import (
    POSE_CSV_HEADER,
    Camera,
    Detection2D,
    GtInfo,
    GtInstance,
    MultiviewTarget,
    ObjectModel,
    PoseEstimate,
    Target,
    make_pose,
)
from threept_jax.data.bop.writer import (
    BopSceneWriter,
    write_camera_info,
)

__all__ = [
    "CELL_FILE",
    "MULTIVIEW_TARGETS_FILE",
    "POSE_CSV_HEADER",
    "BopDataset",
    "BopScene",
    "BopSceneWriter",
    "BopSplit",
    "Camera",
    "Detection2D",
    "GtInfo",
    "GtInstance",
    "MultiviewTarget",
    "ObjectModel",
    "PoseEstimate",
    "Target",
    "check_consistent_times",
    "compute_model_info",
    "load_cell",
    "load_models",
    "load_models_info",
    "load_multiview_targets",
    "load_targets",
    "make_pose",
    "mask_to_rle",
    "read_detection_results",
    "read_pose_results",
    "rle_to_mask",
    "top_estimates_per_image",
    "write_camera_info",
    "write_detection_results",
    "write_cell",
    "write_json_atomic",
    "write_models_info",
    "write_multiview_targets",
    "write_pose_results",
    "write_targets",
]
