"""BOP evaluation: pose errors (MSSD, MSPD, ADD, ADD-S), 6D AP / AP-mm / AR, COCO 2D AP.

The numbers reproduce the official BOP toolkit; `bop6d` and `coco` document which toolkit
behaviour is followed and where. Command line: ``python -m threept_jax.eval --help``.
"""

from threept_jax.eval.bop6d import ImageGt, PoseScores, evaluate_poses
from threept_jax.eval.bop_eval import (
    evaluate_detection_results,
    evaluate_pose_results,
    evaluate_results_file,
)
from threept_jax.eval.coco import evaluate_coco
from threept_jax.eval.pose_error import (
    add,
    adi,
    mspd,
    mspd_pairs,
    mssd,
    mssd_pairs,
    prepare_model,
    rotation_error_deg,
    translation_error,
)

__all__ = [
    "ImageGt",
    "PoseScores",
    "evaluate_poses",
    "evaluate_detection_results",
    "evaluate_pose_results",
    "evaluate_results_file",
    "evaluate_coco",
    "add",
    "adi",
    "mspd",
    "mspd_pairs",
    "mssd",
    "mssd_pairs",
    "prepare_model",
    "rotation_error_deg",
    "translation_error",
]
