"""What a batch did: :class:`BatchSummary` (one result dict per input), as text or JSON."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..data.mosaic import band_labels
from ..files.jsonsafe import json_safe
from ..io.corrected import SUFFIX
from .plan import REFLECTANCE_SUFFIX

__all__ = ["BatchSummary"]


@dataclass
class BatchSummary:
    """What a batch did: one result dict per input (see :func:`correct_file`)."""

    results: list
    seconds: float
    outdir: str
    calibration: dict
    pipeline: dict
    ignored: list = field(default_factory=list)
    #: how it ran: :meth:`hsiffc.batch.workers.WorkerPlan.to_dict` and its ``text``, or the
    #: ``scheduler`` address
    execution: dict = field(default_factory=dict)
    #: files in the input folders that are not read (not an image format hsiffc reads)
    unread: list = field(default_factory=list)

    def _with(self, status):
        return [r for r in self.results if r["status"] == status]

    @property
    def done(self):
        """Results of the files corrected in this run."""
        return self._with("done")

    @property
    def skipped(self):
        """Results of the files skipped (outputs complete and up to date, or left out: see
        :attr:`left_out`)."""
        return self._with("skipped")

    @property
    def left_out(self):
        """Results of the files left out (among the skipped): darks by their metadata."""
        return [r for r in self.results if r.get("left_out")]

    @property
    def failed(self):
        """Results of the files that failed, each with its reason."""
        return self._with("failed")

    @property
    def exit_status(self) -> int:
        """0 when every file is done or skipped, 1 when any failed."""
        return 1 if self.failed else 0

    def uniformity(self):
        """Per band (before, after) non-uniformity, mean over the light frames of done files.

        None when no done file has figures, or when the files have different numbers of bands
        (mosaics of different sizes cannot be pooled band by band; each file's figures stay in
        its result).
        """
        rows = self._measured()
        if not rows or len(self._band_counts(rows)) > 1:
            return None
        w = np.array([r["light_frames"] for r in rows], float)[:, None]
        out = []
        for key in ("uniformity_before", "uniformity_after"):
            v = np.array([[np.nan if x is None else x for x in r[key]] for r in rows], float)
            ok = np.isfinite(v)
            total = (np.where(ok, v, 0.0) * w).sum(0)
            weight = (ok * w).sum(0)
            out.append(np.where(weight > 0, total / np.maximum(weight, 1e-300), np.nan))
        return out[0], out[1]

    def _measured(self) -> list:
        """Results of done files with non-uniformity figures before and after."""
        return [r for r in self.done if r["uniformity_before"] is not None
                and r["uniformity_after"] is not None]

    @staticmethod
    def _band_counts(rows) -> set:
        return {len(r[key]) for r in rows for key in ("uniformity_before", "uniformity_after")}

    def warnings(self) -> dict:
        """Per warning class, the number of files that gave it and their names (relative
        to their input folder), in the order first seen: ``{class: {"count", "files"}}``."""
        out: dict = {}
        for r in self.results:
            for w in r["warnings"]:
                entry = out.setdefault(w["class"], {"count": 0, "files": []})
                entry["count"] += 1
                entry["files"].append(r["rel"])
        return out

    def to_dict(self) -> dict:
        """JSON-safe summary with one result per file (``--json``); ``seconds`` is the whole
        job (reading, correcting and writing every format), ``bytes_written`` the size of the
        files this run wrote."""
        u = self.uniformity()
        return json_safe({"outdir": self.outdir, "seconds": self.seconds,
                          "bytes_written": sum(r.get("bytes_written") or 0 for r in self.done),
                          "counts": {s: len(self._with(s)) for s in ("done", "skipped", "failed")},
                          "exit_status": self.exit_status, "calibration": self.calibration,
                          "pipeline": self.pipeline, "ignored": [str(p) for p in self.ignored],
                          "unread": [str(p) for p in self.unread],
                          "left_out": [r["rel"] for r in self.left_out],
                          "execution": self.execution, "warnings": self.warnings(),
                          "uniformity_before": None if u is None else u[0],
                          "uniformity_after": None if u is None else u[1],
                          "results": self.results})

    def to_text(self) -> str:
        """The summary the command line prints at the end of a batch."""
        done = self.done
        frames = sum(r["frames"] for r in done)
        mb = sum(r["bytes"] for r in done) / 1e6
        t = max(self.seconds, 1e-9)
        written = sum(r.get("bytes_written") or 0 for r in done) / 1e6
        lines = [f"{len(self.results)} files: {len(done)} done, {len(self.skipped)} skipped, "
                 f"{len(self.failed)} failed; {frames} frames corrected and written in "
                 f"{self.seconds:.1f} s, the whole job ({frames / t:.2f} frames/s, "
                 f"{mb / t:.1f} MB/s of input; {written:.1f} MB written)"]
        if self.execution.get("text"):
            lines.append(self.execution["text"])
        lines += [f"note: {n}" for n in self.pipeline.get("notes", [])]
        if self.ignored:
            lines.append(f"ignored {len(self.ignored)} files named like outputs of hsiffc "
                         f"correct (*{SUFFIX}, *{REFLECTANCE_SUFFIX} and their cubes)")
        if self.left_out:
            lines.append(f"left out {len(self.left_out)} files of dark frames (their metadata "
                         f"says kind dark; --kind corrects them anyway): "
                         f"{', '.join(r['rel'] for r in self.left_out)}")
        if self.unread:
            lines.append(f"not read: {len(self.unread)} files that are not an image format "
                         "hsiffc reads (.tif/.tiff, .png, .hdr, .fits): "
                         f"{', '.join(_short(self.unread))}")
        u = self.uniformity()
        counts = self._band_counts(self._measured())
        if len(counts) > 1:
            lines.append("non-uniformity per band: not pooled, the files have "
                         f"{' and '.join(str(n) for n in sorted(counts))} bands (each file's "
                         "figures are in the --json results)")
        if u is not None:
            lines.append("non-uniformity per band (eq. 6, %, mean over light frames, pixels "
                         "good in input and output): input less the pipeline's dark -> corrected")
            first = self._measured()[0]  # bands by wavelength, named as everywhere
            names, order = first.get("band_labels"), first.get("band_order")
            if not names or len(names) != len(u[0]):  # e.g. a cube of virtual bands
                names, order = band_labels(len(u[0])), range(len(u[0]))
            lines += [f"  {names[i]}: {_pct(u[0][i])} -> {_pct(u[1][i])}" for i in order]
        redone = [r for r in self.results if r.get("redone")]
        if redone:
            lines.append("redone:")
            lines += [f"  {r['rel']}: {r['redone']}" for r in redone]
        by_class = self.warnings()
        if by_class:
            n = len({f for c in by_class.values() for f in c["files"]})
            lines.append(f"warnings in {n} file{'s' if n != 1 else ''} (each file's records "
                         "are in the --json results and its output's provenance):")
            lines += [f"  {name}: {c['count']} file{'s' if c['count'] != 1 else ''} "
                      f"({', '.join(c['files'])})" for name, c in by_class.items()]
        if self.failed:
            lines.append("failed:")
            lines += [f"  {r['rel']}: {r['reason']}" for r in self.failed]
        lines.append(f"outputs in {self.outdir}")
        return "\n".join(lines)


def _pct(value) -> str:
    """A non-uniformity for the summary table ("n/a" where none could be measured)."""
    return f"{value:7.3f}" if np.isfinite(value) else "    n/a"


def _short(paths, limit: int = 8) -> list:
    """Up to ``limit`` file names, then how many more."""
    names = [str(p) for p in paths[:limit]]
    return names + ([f"and {len(paths) - limit} more"] if len(paths) > limit else [])
