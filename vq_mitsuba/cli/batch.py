"""`vq-mitsuba batch`: many fits as Ray tasks (`vq_mitsuba.batch.run_batch`)."""

from __future__ import annotations

import sys
from pathlib import Path

from vq_mitsuba.cli.common import command_config, help_config, output_option, positive_int


def add_parser(sub, shared) -> None:
    b = sub.add_parser(
        "batch", parents=[shared["threads"], shared["device"], output_option("the batch's folder: one run per capture and seed",
                                                           metavar="OUT", required=True),
                          shared["config"], shared["size"], shared["quiet"]],
        help="fit many captures (and seeds) at once as Ray tasks, here or on a cluster",
        description="Fit each CAPTURE under each seed into OUT/<capture>[-<preset>]-s<seed>/ with the ordinary "
                    "`fit` (and `eval` with --eval: against the ground truth of a make-scene dataset, else the "
                    "held-out views), each as a Ray task reserving --threads-per-run CPUs. Without --address "
                    "Ray starts on this machine's cores. Rerun the command to skip finished runs and resume the "
                    "others. Writes OUT/batch.json (each run's status), OUT/logs/, OUT/summary.csv and "
                    "OUT/summary.md; exits 1 when a run failed.")
    b.add_argument("captures", nargs="+", metavar="CAPTURE", help="captures to fit (any format `fit` reads)")
    b.add_argument("--seeds", default="0", metavar="S,S,...", help="fit each capture once per seed (default 0)")
    b.add_argument("--eval", action="store_true", help="score each run after its fit (`vq-mitsuba eval`)")
    b.add_argument("--address", metavar="ADDR", help="join this running Ray cluster (e.g. ray://HEAD:10001 or auto)")
    b.add_argument("--threads-per-run", type=positive_int, default=1, metavar="N",
                   help="CPU threads each run reserves and uses (default 1)")
    b.set_defaults(func=run, resume=False)


def run(args) -> int:
    from vq_mitsuba.batch import parse_seeds, run_batch

    if args.help_config:
        return help_config()
    command_config(args)  # bad keys and values fail before any run starts
    fit_args = [x for key in ("downscale", "max_size") if getattr(args, key) is not None
                for x in (f"--{key.replace('_', '-')}", str(getattr(args, key)))]
    device = ["--device", args.device] if args.device != "auto" else []  # each fit and eval chooses its own
    fit_args += device
    fit_args += [x for item in args.set for x in ("--set", item)]
    fit_args += ["--config", str(Path(args.config).resolve())] if args.config else []
    rows = run_batch(args.captures, args.output, seeds=parse_seeds(args.seeds), presets=[args.preset],
                     fit_args=fit_args, threads=args.threads_per_run, evaluate=args.eval, address=args.address,
                     eval_args=device)
    done = sum(r.get("status") == "done" for r in rows)
    for row in rows:
        if row.get("status") != "done":
            print(f"{row['run']}: {row.get('status', 'not run')}: {row.get('message', '')}", file=sys.stderr)
    print(f"{done} of {len(rows)} runs done; summary in {args.output}/summary.md and summary.csv")
    return 0 if done == len(rows) else 1
