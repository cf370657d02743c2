"""The ``dataset`` subcommand: ``fmbrdf-mi dataset --config CONFIG --out DIR [--shard I/N]``.

:func:`add_dataset_arguments` and :func:`run_dataset` follow the subcommand
protocol of :mod:`fmbrdf_mi.cli`, which reports errors (ValueError and its
subclasses: bad config keys, --shard, ...) as one line.
"""
from __future__ import annotations

import argparse
import os

HELP = "render a synthetic polarimetric dataset (Stokes EXR, normals, mask, labels) from a config"
EPILOG = """\
examples:
  fmbrdf-mi dataset --config scenes/dataset_example.toml --out data/train
  fmbrdf-mi dataset --config scenes/dataset_example.toml --out data/train --shard 3/8
  (SLURM array: --shard $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT)

Rerunning the same command resumes an interrupted run: finished samples are
kept, the rest rendered.  Shards are numbered from 0; shard I renders the
samples with index % N == I.  Run them into one shared directory, or copy the
shard directories into one and rerun without --shard to write manifest.jsonl.
The config format is documented in scenes/dataset_example.toml."""


def add_dataset_arguments(p):
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG
    p.add_argument("--config", required=True, metavar="CONFIG",
                   help="dataset configuration, .toml or .json (builtin:dataset_example: the documented example "
                        "shipped with the package)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created; resumed if it exists)")
    p.add_argument("--shard", metavar="I/N", default=None,
                   help="render only shard I of N (0 <= I < N): samples with index %% N == I")
    p.add_argument("--seed", type=int, default=None, help="override the config's seed")
    p.add_argument("--samples", type=int, default=None, metavar="N", help="override the config's sample count")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output, only the summary")


def run_dataset(args):
    from . import config_path, generate, load_config, parse_shard, read_config_file

    parse_shard(args.shard)  # report argument mistakes before importing Mitsuba
    args.config = config_path(args.config)  # builtin:dataset_example -> the shipped example
    raw = read_config_file(args.config)
    if args.seed is not None:
        raw["seed"] = args.seed
    if args.samples is not None:
        raw["samples"] = args.samples
    cfg = load_config(raw, base_dir=os.path.dirname(os.path.abspath(args.config)))
    summary = generate(cfg, args.out, shard=args.shard, progress=not args.quiet)
    if args.quiet:
        print(f"{summary['rendered']} samples rendered ({summary['skipped']} already done) in "
              f"{summary['seconds']:.1f} s, {summary['samples_per_second']:.2f} samples/s")
    return 0
