"""Which trainer a config runs, for ``train/launch.py`` and ``train/adapt.py``.

The base :class:`train.trainer.Trainer` knows neither model; each concrete trainer imports it.
The choice between them is made here, from ``config.trainer``.
"""

from __future__ import annotations

from train.trainer import Trainer
from train.trainer_detector import DetectorTrainer
from train.trainer_refiner import RefinerTrainer


def trainer_class(config) -> type[Trainer]:
    """The trainer of ``config.trainer``: ``"refiner"`` trains 3PT-R (:class:`RefinerTrainer`),
    anything else 3PT-D (:class:`DetectorTrainer`)."""
    return RefinerTrainer if config.trainer == "refiner" else DetectorTrainer
