"""Training logs: TensorBoard event files, console lines and a progress bar.

Only process 0 writes (event files in ``<workdir>/tb``); every process keeps its bar off but
still averages metrics, so multi-host runs print once. When the output is not a terminal (a
log file, CI) there is no bar, whose redraws would fill the file: the step lines, which name
the step of the total, are the progress. Scalars are averaged over the steps
since the last write.

A run resumed from step S may find events of steps after S in ``tb/``: its previous process
logged them before dying and the resumed run logs those steps again. The resumed run's event
file therefore starts with a ``SessionLog.START`` at step S + 1 (tensorboardX ``purge_step``),
on which TensorBoard drops every earlier-read event at step S + 1 or later, so each step shows
once. Its file name carries ``.resumed<S>`` so that it sorts after the dead run's file even
when both were opened within the same second (tensorboardX names files by the second).
"""

from __future__ import annotations

import math
import pathlib
import sys
import time
from collections.abc import Mapping

import tqdm

from threept_jax.data.run_dir import TB_DIR


class MetricLogger:
    """Averages per-step scalars and writes them every ``log_every`` steps."""

    def __init__(self, workdir, *, total_steps: int, start_step: int, examples_per_step: int,
                 enabled: bool = True, progress_bar: bool = True):
        self.enabled = enabled
        self.examples_per_step = examples_per_step
        self.total_steps = total_steps
        self._sums: dict[str, float] = {}
        self._count = 0
        self._t0 = time.perf_counter()
        self._steps_since = 0
        self.writer = None
        self.bar = None
        if enabled:
            from tensorboardX import SummaryWriter

            resume = {"purge_step": start_step + 1,
                      "filename_suffix": f".resumed{start_step}"} if start_step else {}
            self.writer = SummaryWriter(str(pathlib.Path(workdir) / TB_DIR), **resume)
            if progress_bar and sys.stderr.isatty():
                self.bar = tqdm.tqdm(total=total_steps, initial=start_step, unit="step",
                                     dynamic_ncols=True, desc="train")

    def update(self, metrics: Mapping[str, float]) -> None:
        """Add one step's scalars (host floats)."""
        for k, v in metrics.items():
            self._sums[k] = self._sums.get(k, 0.0) + float(v)
        self._count += 1
        self._steps_since += 1
        if self.bar is not None:
            self.bar.update(1)

    def reset_clock(self) -> None:
        """Restart the throughput clock (after compilation, evaluation or checkpointing)."""
        self._t0 = time.perf_counter()
        self._steps_since = 0

    def flush(self, step: int) -> dict[str, float]:
        """Write the averages since the last flush at ``step``; returns them."""
        if not self._count:
            return {}
        means = {k: v / self._count for k, v in self._sums.items()}
        elapsed = time.perf_counter() - self._t0
        if self._steps_since and elapsed > 0:
            means["examples_per_s"] = self._steps_since * self.examples_per_step / elapsed
            means["step_time_s"] = elapsed / self._steps_since
        self._sums, self._count = {}, 0
        self.reset_clock()
        self.write(step, {f"train/{k}": v for k, v in means.items()})
        return means

    def write(self, step: int, scalars: Mapping[str, float]) -> None:
        """Scalars to TensorBoard and one console line (process 0 only)."""
        if not self.enabled:
            return
        for k, v in scalars.items():
            self.writer.add_scalar(k, float(v), step)
        self.writer.flush()
        self.print(f"step {step}/{self.total_steps}: " + ", ".join(
            f"{k.split('/', 1)[-1]}={_fmt(v)}" for k, v in sorted(scalars.items())))
        if self.bar is not None and "train/examples_per_s" in scalars:
            self.bar.set_postfix(ex_per_s=f"{scalars['train/examples_per_s']:.1f}",
                                 loss=_fmt(scalars.get("train/loss", math.nan)))

    def print(self, text: str) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.write(text)
        else:
            print(text, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.writer is not None:
            self.writer.close()


def _fmt(v: float) -> str:
    v = float(v)
    if v == 0 or not math.isfinite(v):
        return str(v)
    return f"{v:.4g}" if 1e-3 <= abs(v) < 1e5 else f"{v:.3e}"
