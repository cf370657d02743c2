"""The one skeleton of every fit the command writes: :class:`FitJob`.

    report = SingleImage(inputs, out, ...).run()      # what fit_files(inputs, out, ...) does

Every mode of ``fmbrdf-mi fit`` (one image, several images, a colour mosaic,
several colour mosaics, the normal refinement) is a subclass that fills in
the steps; :meth:`FitJob.run` alone decides their order and does what they
share, as Mitsuba's differentiable integrators share one base that runs the
passes while each variant overrides one method:

1. :meth:`~FitJob.check`: the options, before any file is read;
2. :meth:`~FitJob.files`: the output paths (``fit.json`` first), refused
   if any exists and ``force`` is not given (:func:`fmbrdf_mi.fit.outputs.writer.prepare`);
3. :meth:`~FitJob.read`, :meth:`~FitJob.fit`: inputs to observations, the
   library API (:mod:`fmbrdf_mi.fit.api`);
4. :meth:`~FitJob.report`: the dict that becomes ``fit.json``;
5. :meth:`~FitJob.write`: plots and the other output files;
6. ``fit.json``, written last and atomically (one JSON encoder), so a run
   that fails on the way leaves no record of a fit it did not finish.

The run returns the report (what the summary, :func:`fmbrdf_mi.fit.outputs.summary.print_summary`, prints).
"""
from __future__ import annotations

import os
import time

from fmbrdf_mi.fit.outputs.writer import prepare, write_json


class FitJob:
    """One run of a fit that writes its outputs into ``out`` (module docstring).  Subclasses fill in the steps."""

    def __init__(self, out, *, force=False, progress=True, command=None):
        self.out, self.force, self.progress, self.command = out, force, progress, command
        self.t0 = time.time()

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
        """The outputs besides ``fit.json`` (plots, maps, images); ``report`` may still be added to."""

    def finish(self, report):
        """What :meth:`run` returns (the report, with what the summary needs besides fit.json)."""
        return report

    def run(self):
        self.check()
        paths = list(self.files())
        prepare(self.out, paths, self.force)
        self.read()
        self.fit()
        report = self.report()
        os.makedirs(self.out, exist_ok=True)
        self.write(report)
        write_json(paths[0], report)
        self.paths = paths
        return self.finish(report)
