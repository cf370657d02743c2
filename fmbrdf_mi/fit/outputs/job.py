"""The one skeleton of every fit the command writes: :class:`FitJob`, whose subclasses are the modes of
``fmbrdf-mi fit``.

:meth:`FitJob.run` checks the options, locks ``out``, refuses existing outputs without ``force``, reads, fits
and writes into a staging directory whose files replace the old ones (``fit.json`` last, stale outputs
removed) only when all are written: a failed or interrupted run leaves ``out`` as it was.  Writing a whole
frame's figures and maps takes a while: past a few seconds a line per file written gives the time left
(:class:`~fmbrdf_mi._paths.StageProgress`, as ``fmbrdf-mi render`` does), none without ``progress``.
"""
from __future__ import annotations

import os
import time

from fmbrdf_mi._paths import StageProgress, locked_directory, staged_directory
from fmbrdf_mi.fit.outputs.writer import prepare, relocate, stale_outputs, write_json


class FitJob:
    """One run of a fit that writes its outputs into ``out`` (module docstring).  Subclasses fill in the steps."""

    def __init__(self, out, *, force=False, progress=True, command=None):
        self.out, self.force, self.progress, self.command = out, force, progress, command
        self.t0 = time.time()
        self.bar = None

    def check(self):
        """Check the options before any file is read (raise :class:`~fmbrdf_mi.fit.errors.InputError`)."""

    def files(self):
        """The output paths, ``fit.json`` first."""
        raise NotImplementedError

    def read(self):
        """Read the inputs (observations, samples) into the job."""

    def fit(self):
        """Run the fit (the library API) on what :meth:`read` read."""
        raise NotImplementedError

    def report(self):
        """The dict written to ``fit.json``."""
        raise NotImplementedError

    def write(self, report):
        """The outputs besides ``fit.json`` (plots, maps, images), each passed to :meth:`wrote` once written;
        ``report`` may still be added to."""

    def wrote(self, path):
        """The output ``path`` is written: a step of the writing's progress."""
        if self.bar is not None:
            self.bar.step(os.path.basename(path))

    def run(self):
        """Run the steps; returns the report plus the files written and the wall time (not in fit.json)."""
        self.check()
        with locked_directory(self.out):
            paths = list(self.files())
            prepare(self.out, paths, self.force)
            self.read()
            self.fit()
            report = self.report()
            out, record = self.out, os.path.basename(paths[0])
            with staged_directory(out, last=(record,), remove=stale_outputs(out, paths)) as stage:
                self.out = stage
                self.bar = StageProgress("writing", len(paths), enabled=bool(self.progress))
                try:
                    self.files()       # the paths of the write phase, in the staging directory
                    self.write(report)
                    report = relocate(report, stage, out)
                    write_json(os.path.join(stage, record), report)
                    self.wrote(record)
                finally:
                    self.out, self.bar = out, None
                    self.files()
        report["outputs"], report["wall_s"] = paths, time.time() - self.t0
        return report
