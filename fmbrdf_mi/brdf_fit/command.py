"""The ``fit-brdf`` subcommand: ``fmbrdf-mi fit-brdf FILE.binary [-o DIR]``, or a batch of files.

Follows the subcommand protocol of :mod:`fmbrdf_mi.cli` (user errors, a
ValueError or OSError, become one line and exit status 1).

Batch (several FILEs, or a directory of ``*.binary`` files): every material
is fitted as a single run would (the same options, the same outputs in its
own directory), by ``--jobs`` worker processes; a material that fails (an
unreadable file, outputs that exist without ``--force``) is one line naming
its file on stderr, the others are still fitted, and the exit status is 1.
The summary table (one row per material) goes to stdout and, with ``-o``, to
DIR/summary.tsv.  Ctrl-C stops a batch at once: the queued materials are not
fitted, the running fits are stopped, and a material's files are written all or
none (:func:`fmbrdf_mi._paths.staged_directory`), so no params.json is half-written.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time

HELP = "fit FMBRDF (shared eta, alpha, beta, kappa; per-channel k_s, k_b) to MERL BRDF binary files"
EPILOG = """\
examples:
  fmbrdf-mi fit-brdf brdfs/blue-acrylic.binary
  fmbrdf-mi fit-brdf brdfs/blue-acrylic.binary -o fits/blue-acrylic --samples 100000 --starts 3
  fmbrdf-mi fit-brdf brdfs/ -o fits --jobs 2          # every brdfs/*.binary -> fits/NAME/, fits/summary.tsv

Writes DIR/params.json (parameters, log10 RMSE on the fitted samples and on
every usable bin, per channel, the samples used and the timings) and
DIR/slices.png (measured against fitted BRDF slices).  The error is the RMS of
log10(f_fit) - log10(f_measured), as in the FMBRDF authors' MERL fits.

Several FILEs or a directory: a batch.  Each material goes to DIR/NAME/ with
-o DIR (NAME: the file name without extension), else next to its file
(FILE without extension + _fit); the summary table to stdout and to
DIR/summary.tsv.  A material that fails is reported in one line naming its
file and the others are still fitted (exit status 1).  --skip-existing
leaves the materials with a params.json alone and rewrites the summary
(resuming a batch)."""

OUTPUTS = ("params.json", "slices.png")
SUMMARY = "summary.tsv"
#: The summary table's columns.
COLUMNS = ("material", "status", "eta", "alpha", "beta", "kappa", "k_s", "k_b", "log10_rmse_all", "at_bound",
           "seconds", "out")


def add_fit_brdf_arguments(p):
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG
    p.add_argument("file", metavar="FILE", nargs="+",
                   help="MERL BRDF binary (.binary); several, or a directory of them: a batch")
    p.add_argument("-o", "--out", metavar="DIR",
                   help="output directory (default: FILE without extension + _fit); batch: one subdirectory "
                        "per material")
    p.add_argument("--samples", type=int, default=50_000, metavar="N",
                   help="bins fitted (a seeded random subset of the usable ones; default 50000)")
    p.add_argument("--starts", type=int, default=2, metavar="K", help="refine the K best start-grid points")
    p.add_argument("--max-evals", type=int, default=60, metavar="N", help="error evaluations per refinement")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample subset")
    p.add_argument("--full-grid", action="store_true",
                   help="evaluate every start-grid point (default: coarse to fine, which finds the same best "
                        "points on smooth error surfaces in about 45 %% of the evaluations)")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="batch: materials fitted at once (processes; one FILE is fitted in this process)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--skip-existing", action="store_true",
                   help="leave materials whose params.json exists as they are (listed in the summary; not with --force)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output, only the summary")
    from .mueller_command import add_mueller_arguments

    add_mueller_arguments(p)


def _options(args):
    from .fitting import BRDFFitOptions

    return BRDFFitOptions(max_samples=args.samples, starts=args.starts, max_evals=args.max_evals, seed=args.seed,
                          **({"grid_search": "full"} if args.full_grid else {}))


def _check_args(args):
    for name, v, lo in (("--samples", args.samples, 100), ("--starts", args.starts, 1),
                        ("--max-evals", args.max_evals, 1), ("--jobs", args.jobs, 1)):
        if v < lo:
            raise ValueError(f"{name}: must be an integer >= {lo}, got {v}")
    if args.force and args.skip_existing:
        raise ValueError("--force and --skip-existing: give one of them (--force fits every material again over "
                         "its outputs, --skip-existing leaves the fitted ones as they are)")


def _check_outputs(out, force):
    """Refuse (FileExistsError) before the fit if outputs exist without ``force``."""
    from fmbrdf_mi._paths import check_output_dir

    check_output_dir(out)   # before the fit (seconds to minutes), as the overwrite refusal below
    existing = [os.path.join(out, f) for f in OUTPUTS if os.path.exists(os.path.join(out, f))]
    if existing and not force:
        raise FileExistsError(f"{existing[0]} exists; pass --force to overwrite it")


def fit_one(path, out, opts, force=False, progress=None):
    """Fit one MERL file and write ``out``/params.json and slices.png: the report (dict, as params.json)."""
    from fmbrdf_mi._paths import staged_directory

    from . import fitting
    from .merl import read_merl
    from .plots import PHI_D_INDEX, slice_plot

    _check_outputs(out, force)
    t0 = time.time()
    brdf = read_merl(path)
    res = fitting.fit_brdf(brdf, opts, progress=progress)
    name = os.path.splitext(os.path.basename(path))[0]
    fitted = fitting.model_brdf(res.params, PHI_D_INDEX)  # the plotted slices only
    with staged_directory(out, last=("params.json",)) as stage:   # both files or neither (Ctrl-C)
        slice_plot(brdf, fitted, os.path.join(stage, "slices.png"),
                   title=f"{name}: FMBRDF fit, log10 RMSE {res.log_rmse_all:.3f} (all usable bins)")
        report = {"file": os.path.abspath(path), "params": res.params,
                  "log10_rmse": {"fitted_samples": res.log_rmse, "all_usable_bins": res.log_rmse_all,
                                 "per_channel_fitted_samples": dict(zip("rgb", res.log_rmse_channels))},
                  "converged": res.converged, "stop_reason": res.stop_reason,
                  "n_samples": res.n_samples, "n_usable_bins": res.n_usable, "at_bound": res.at_bound,
                  "options": opts.__dict__, "history": res.history,
                  "timings": dict(res.timings, command=time.time() - t0)}
        with open(os.path.join(stage, "params.json"), "w") as f:
            json.dump(report, f, indent=2, default=float)
    return report


def summary_line(name, report, out):
    """The one-line result of a material (stdout)."""
    p = report["params"]
    at_bound = report["at_bound"]
    return (f"{name}: eta {p['eta']:.4g}, alpha {p['alpha']:.4g}, beta {p['beta']:.4g}, kappa {p['kappa']:.4g}, "
            f"k_s {', '.join(f'{v:.4g}' for v in p['k_s'])}, k_b {', '.join(f'{v:.4g}' for v in p['k_b'])}; "
            f"log10 RMSE {report['log10_rmse']['all_usable_bins']:.4f} over {report['n_usable_bins']} bins"
            + (f"; at the bound: {', '.join(at_bound)}" if at_bound else "") + f" -> {out}")


def _not_converged(report):
    from fmbrdf_mi.fit.outputs.summary import EXIT_NOT_CONVERGED

    print(f"fmbrdf-mi fit-brdf: NOT converged ({report['stop_reason']}): the parameters are the last accepted "
          f"ones; raise --max-evals (exit status {EXIT_NOT_CONVERGED})", file=sys.stderr)
    return EXIT_NOT_CONVERGED


def run_fit_brdf(args):
    _check_args(args)
    from .mueller import is_mueller_table
    from .mueller_command import refuse_mueller_options, run_fit_mueller

    if any(is_mueller_table(f) for f in args.file):   # a Mueller-matrix BRDF table: mueller_command.py
        return run_fit_mueller(args)
    refuse_mueller_options(args)
    files = _inputs(args.file)
    if len(files) == 1 and not os.path.isdir(args.file[0]):
        return _run_single(args, files[0])
    return _run_batch(args, files)


def _run_single(args, path):
    out = args.out or os.path.splitext(path)[0] + "_fit"
    name = os.path.splitext(os.path.basename(path))[0]
    if args.jobs != 1:
        print(f"fmbrdf-mi fit-brdf: --jobs {args.jobs}: one FILE is fitted in this process (--jobs fits the "
              "materials of a batch in parallel)", file=sys.stderr, flush=True)
    if args.skip_existing and os.path.exists(os.path.join(out, "params.json")):
        try:
            with open(os.path.join(out, "params.json")) as f:
                line = summary_line(name, json.load(f), out)
        except (OSError, ValueError, KeyError, TypeError):
            line = None   # unreadable or incomplete: fitted again (needs --force to overwrite)
        if line is not None:
            print(f"{line} (skipped: params.json exists)")
            return 0
    progress = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    report = fit_one(path, out, _options(args), args.force, progress)
    print(summary_line(name, report, out))
    return 0 if report["converged"] else _not_converged(report)


def _inputs(items):
    """The MERL files of the FILE arguments: files as given, directories' ``*.binary`` sorted by name."""
    files = []
    for item in items:
        if os.path.isdir(item):
            found = sorted(os.path.join(item, f) for f in os.listdir(item) if f.endswith(".binary")
                           and os.path.isfile(os.path.join(item, f)))
            if not found:
                raise FileNotFoundError(f"{item}: a directory without *.binary files")
            files += found
        else:
            files.append(item)
    return files


def _error_line(path, exc):
    """One line naming the file: an OSError's path and reason, or the message (prefixed by the file)."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}"
    else:
        text = " ".join(str(exc).split()) or type(exc).__name__
    return text if path in text else f"{path}: {text}"


def _batch_task(path, out, opts, force, threads=None):
    """One material of a batch (in a worker process, or in this one): (report or None, error line or None)."""
    if threads:
        import drjit as dr

        dr.set_thread_count(threads)
    global _fitting
    _fitting = True
    try:
        return fit_one(path, out, opts, force), None
    except (ValueError, OSError) as e:   # the CLI's user errors: the file's problem, not the batch's
        return None, _error_line(path, e)
    except BaseException as e:
        from fmbrdf_mi.interrupt import interrupted

        if interrupted(e) and multiprocessing.parent_process() is not None:
            os._exit(130)   # a worker stopped by the batch (_stop_workers): its outputs removed, no further material
        raise
    finally:
        _fitting = False


def _worker_signals():
    """A batch worker's signals: Ctrl-C (sent to the terminal's whole process group) is left to the batch,
    which stops the workers with SIGTERM (:func:`_stop_workers`); SIGTERM ends the worker's fit as a
    KeyboardInterrupt would, so that its staged outputs are removed (:func:`fit_one`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminated)


#: Whether this worker is fitting a material (SIGTERM then stops the fit; otherwise the worker exits at once).
_fitting = False


def _terminated(signum, frame):
    if _fitting:
        raise KeyboardInterrupt
    os._exit(130)


def _stop_workers(grace=10.0):
    """Stop this process's worker processes: SIGTERM (a fit stops, its staging directory removed), then,
    after ``grace`` seconds, SIGKILL for those still running."""
    workers = multiprocessing.active_children()
    for w in workers:
        w.terminate()
    deadline = time.time() + grace
    for w in workers:
        w.join(max(0.0, deadline - time.time()))
        if w.is_alive():
            w.kill()
            w.join()


def _remove_partial(existed):
    """After the workers are stopped: the staging directories a killed worker could not remove, and the
    output directories the batch made that are left empty (``existed``: {output directory: whether it
    existed before the batch})."""
    import glob
    import shutil

    for out, was in existed.items():
        for stage in glob.glob(os.path.join(glob.escape(out), ".staging.*.partial")):
            shutil.rmtree(stage, ignore_errors=True)
        if not was and os.path.isdir(out) and not os.listdir(out):
            os.rmdir(out)


def _row(name, status, report, out, seconds):
    if report is None:
        return {**dict.fromkeys(COLUMNS, ""), "material": name, "status": status, "out": out}
    p = report["params"]
    return {"material": name, "status": status, **{k: f"{p[k]:.6g}" for k in ("eta", "alpha", "beta", "kappa")},
            "k_s": " ".join(f"{v:.6g}" for v in p["k_s"]), "k_b": " ".join(f"{v:.6g}" for v in p["k_b"]),
            "log10_rmse_all": f"{report['log10_rmse']['all_usable_bins']:.6g}",
            "at_bound": " ".join(report["at_bound"]), "seconds": f"{seconds:.1f}" if seconds is not None else "",
            "out": out}


def _run_batch(args, files):
    from fmbrdf_mi._paths import check_output_dir
    from fmbrdf_mi.fit.outputs.summary import EXIT_NOT_CONVERGED

    names = [os.path.splitext(os.path.basename(f))[0] for f in files]
    if args.out:
        check_output_dir(args.out)
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"{len(twice)} materials share a name ({', '.join(twice[:3])}): their outputs "
                             f"would go to the same {os.path.join(args.out, twice[0])}; fit them in separate runs")
        if os.path.exists(os.path.join(args.out, SUMMARY)) and not (args.force or args.skip_existing):
            raise FileExistsError(f"{os.path.join(args.out, SUMMARY)} exists; pass --force to overwrite it")
    outs = [os.path.join(args.out, n) if args.out else os.path.splitext(f)[0] + "_fit" for f, n in zip(files, names)]
    say = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    opts = _options(args)
    rows, errors, not_converged = {}, [], []
    todo = []
    for path, name, out in zip(files, names, outs):
        if args.skip_existing and os.path.exists(os.path.join(out, "params.json")):
            try:
                with open(os.path.join(out, "params.json")) as f:
                    rows[path] = _row(name, "skipped (exists)", json.load(f), out, None)
                continue
            except (OSError, ValueError, KeyError, TypeError):
                pass  # unreadable or incomplete: fitted again (needs --force to overwrite)
        todo.append((path, name, out))
    jobs = min(args.jobs, max(len(todo), 1))
    say(f"[fit-brdf] batch of {len(files)} materials: {len(todo)} to fit"
        + (f", {len(files) - len(todo)} skipped (params.json exists)" if len(todo) < len(files) else "")
        + f", {jobs} at a time")
    t0 = time.time()

    def finished(k, path, name, out, result):
        report, err = result
        if err is not None:
            errors.append(err)
            rows[path] = _row(name, "failed", None, out, None)
            print(f"fmbrdf-mi fit-brdf: error: {err}", file=sys.stderr, flush=True)
        else:
            ok = report["converged"]
            if not ok:
                not_converged.append(path)
            rows[path] = _row(name, "ok" if ok else "not converged", report, out, report["timings"]["command"])
        el = time.time() - t0
        left = el / k * (len(todo) - k)
        say(f"[fit-brdf] {k}/{len(todo)} done ({name}: "
            + (f"log10 RMSE {report['log10_rmse']['all_usable_bins']:.4f}" if err is None else "failed")
            + f"); {el:.0f} s" + (f", about {left:.0f} s left" if k < len(todo) else ""))

    if jobs == 1:
        for k, (path, name, out) in enumerate(todo, 1):
            finished(k, path, name, out, _batch_task(path, out, opts, args.force))
    else:
        import concurrent.futures as cf

        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        threads = max(1, cores // jobs)  # Dr.Jit threads per worker: the cores shared out
        existed = {out: os.path.isdir(out) for _, _, out in todo}
        pool = cf.ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_worker_signals)
        try:
            futures = {pool.submit(_batch_task, path, out, opts, args.force, threads): (path, name, out)
                       for path, name, out in todo}
            for k, fut in enumerate(cf.as_completed(futures), 1):
                path, name, out = futures[fut]
                try:
                    result = fut.result()
                except Exception as e:  # a worker that died (out of memory, a crash): named, the rest go on
                    result = (None, _error_line(path, RuntimeError(f"the fit's worker failed: {e}")))
                finished(k, path, name, out, result)
        except BaseException:   # Ctrl-C: the queued materials are not fitted, the running fits stopped
            pool.shutdown(wait=False, cancel_futures=True)
            _stop_workers()
            _remove_partial(existed)
            raise
        pool.shutdown()
    table = [rows[f] for f in files]
    text = "\t".join(COLUMNS) + "\n" + "".join("\t".join(str(r[c]) for c in COLUMNS) + "\n" for r in table)
    if args.out:
        tmp = os.path.join(args.out, SUMMARY + ".part")
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, os.path.join(args.out, SUMMARY))
    sys.stdout.write(text)
    if not_converged:
        print(f"fmbrdf-mi fit-brdf: {len(not_converged)} of {len(files)} materials NOT converged (raise "
              f"--max-evals): {', '.join(not_converged)}" + ("" if errors else f" (exit status {EXIT_NOT_CONVERGED})"),
              file=sys.stderr)
    if errors:
        print(f"fmbrdf-mi fit-brdf: {len(errors)} of {len(files)} materials failed:\n"
              + "\n".join(f"  {e}" for e in errors), file=sys.stderr)
        return 1
    return EXIT_NOT_CONVERGED if not_converged else 0
