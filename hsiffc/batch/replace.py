"""Nothing replaced unasked: a folder's outputs are replaced only by the same job (the same
calibration identity and pipeline fingerprint, which covers the steps, their parameters and
the input options: a resume) or with ``--overwrite``.

:func:`check_replacements` runs once, under the folder's lock, before any file is corrected:
an output of ``hsiffc correct`` made by another job refuses the whole batch in one line naming
that job, so nothing in the folder changes. Outputs of the same job are still redone when
their input changed or they are damaged (:func:`hsiffc.batch.task.stale_reason`).
"""

from __future__ import annotations

from pathlib import Path

from ..cubes.stream import product_present, read_product
from ..errors import DataFormatError
from ..io.corrected import is_corrected_file
from .plan import BatchError

__all__ = ["check_replacements", "describe_job"]


def describe_job(calibration: dict | None, pipeline: dict | None) -> str:
    """A job in a few words: its pipeline (file name or "the default pipeline"), its steps'
    stages, its fingerprint and its calibration (file name and identity, or none)."""
    pipeline = pipeline or {}
    steps = ", ".join(str(s.get("stage")) for s in pipeline.get("steps") or ())
    name = (f"pipeline {Path(pipeline['path']).name}" if pipeline.get("path")
            else "the default pipeline")
    text = f"{name} ({steps or 'no steps'}; fingerprint {pipeline.get('fingerprint')})"
    if not calibration or not calibration.get("identity"):
        return text + ", no calibration"
    where = Path(calibration["path"]).name if calibration.get("path") else "a calibration"
    return text + f", calibration {where} ({calibration['identity']})"


def check_replacements(jobs, ctx, settings) -> None:
    """BatchError naming the existing job when an output this batch would write is an
    output of ``hsiffc correct`` made by another job (unless ``settings.overwrite``).
    Damaged outputs and other files are left to the task (it redoes or refuses them)."""
    if settings.overwrite:
        return
    this = None
    for job, fmt in ((j, f) for j in jobs for f in settings.formats):
        out = Path(job.output)
        present = product_present(out, fmt)
        if not present or any(p.is_symlink() for p in present) or (
                fmt == "tiff" and not is_corrected_file(out)):
            continue
        try:
            prov = read_product(out, fmt)
        except DataFormatError:
            continue  # not complete: redone by the task, which says why
        cal, pipe = prov.get("calibration") or {}, prov.get("pipeline") or {}
        if (cal.get("identity") == ctx.identity
                and pipe.get("fingerprint") == ctx.info["fingerprint"]):
            continue
        if this is None:
            this = describe_job({"identity": ctx.identity, "path": settings.calibration},
                                ctx.info)
        raise BatchError(
            f"{present[0]}: already written by another job, {describe_job(cal, pipe)}; this run is "
            f"{this}. Nothing was changed: correct into another folder, or pass --overwrite "
            "to replace that job's outputs")
