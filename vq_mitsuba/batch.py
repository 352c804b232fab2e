"""Many captures at once: `vq-mitsuba batch CAPTURES... -o OUT`, one Ray task per run.

Each capture, under each preset and seed, is a run `OUT/<capture>[-<preset>]-s<seed>/`, fitted by
the ordinary command (`vq-mitsuba fit ... --resume` in a process of its own, and `vq-mitsuba eval`
after it with `--eval`), inside a Ray task that reserves the CPU threads the fit uses. Ray decides
where the tasks run: on this machine's cores, or across a cluster with `--address`.

Resumable as a whole: `OUT/batch.json` records each finished run; a rerun skips them, and the
others resume from their checkpoints. A fit process that dies by a signal (its worker killed, a
machine lost) or stopped by SIGTERM / SIGINT fails its task as a `RunLost`, which Ray retries, and
the retry resumes. A capture's bad input fails only its own run, with its message. A run goes on
only with its own settings: when the config a rerun asks for differs from the one in the run's
config.yaml, the run is left as it is and reported `refused`, naming the keys that differ. At the
end `OUT/summary.csv` and `OUT/summary.md` hold one row per run (its settings, figures, time and
status; the markdown with a novel view of each run, `OUT/views/<run>.png`, and its material sheet).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from vq_mitsuba import brdf
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.data.unposed import capture_name
from vq_mitsuba.errors import InputError, UserError
from vq_mitsuba.geometry import methods
from vq_mitsuba.run.outputs import BATCH_MARKER, check_output_folder
from vq_mitsuba.run.run_dir import RunDir, read_json, write_atomic, write_json

STATUS = BATCH_MARKER  # the batch's own record: every run's status, the marker of a batch folder
LOGS = "logs"  # OUT/logs/<run>.log: what each run's commands printed
VIEWS = "views"  # OUT/views/<run>.png: one novel view of each finished run, for the summary
VIEW_SIZE, VIEW_SPP = 256, 16  # the long side and samples per pixel of those views
RETRIES = 3  # tries of a run whose process died by a signal
LOCK_WAIT_S = 300.0  # how long a retry waits for the fit of the try before it to let go of the run
MAX_SEED = 2 ** 32 - 1  # the seeds numpy, torch and Mitsuba all take
SEED_KEYS = ("train.seed", *methods.seed_keys())  # the keys the batch sets for each run's seed
REFUSED = "refused"  # the status of a run whose settings differ from the ones a rerun asks for


class RunLost(Exception):
    """A fit or eval process killed by a signal (not a failure of its own): Ray retries the task."""


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One run of the batch: which capture, under which preset and seed, into which folder."""

    name: str
    capture: str
    seed: int
    preset: str | None = None
    args: tuple[str, ...] = ()  # fit options for this capture alone (e.g. its own --config)


def plan(captures: list[str], seeds: list[int], presets: list[str | None],
         capture_args: dict[str, list[str]] | None = None) -> list[RunSpec]:
    """Every capture under every preset and seed (with `capture_args[capture]`, its own fit
    options); two captures of one name are refused (their runs would share a folder)."""
    if not captures:
        raise InputError(None, "batch needs at least one CAPTURE")
    names: dict[str, str] = {}
    for capture in captures:
        name = capture_name(capture)
        if name in names and names[name] != str(Path(capture).resolve()):
            raise InputError(capture, f"shares the name '{name}' with {names[name]}: their runs would share a "
                                      "folder; rename one of the folders")
        names[name] = str(Path(capture).resolve())
    specs = []
    for capture in dict.fromkeys(captures):
        for preset in presets:
            for seed in seeds:
                label = f"{capture_name(capture)}{f'-{preset}' if preset else ''}-s{seed}"
                own = tuple((capture_args or {}).get(capture, ()))
                specs.append(RunSpec(label, str(Path(capture).resolve()), seed, preset, own))
    return specs


def _die_with_parent() -> None:
    """In the fit's process: SIGTERM it when the worker that started it dies (Linux), so that a lost
    worker leaves no fit behind holding the run; SIGTERM ends a fit with a checkpoint."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _command(argv: list[str], log: io.TextIOBase) -> tuple[int, str]:
    """Run `vq-mitsuba ARGV` in a process of its own; (exit code, its last `error:` line)."""
    log.write(f"$ vq-mitsuba {' '.join(argv)}\n")
    log.flush()
    proc = subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", *argv], stdout=log, stderr=subprocess.PIPE,
                          text=True, preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
    log.write(proc.stderr)
    log.flush()
    errors = [line[len("error: "):] for line in proc.stderr.splitlines() if line.startswith("error: ")]
    if proc.returncode < 0:
        raise RunLost(f"vq-mitsuba {argv[0]} was killed by signal {-proc.returncode}")
    if proc.returncode in (128 + signal.SIGTERM, 128 + signal.SIGINT):  # stopped, its checkpoint written
        raise RunLost(f"vq-mitsuba {argv[0]} was stopped by signal {proc.returncode - 128}")
    return proc.returncode, errors[-1] if errors else proc.stderr.strip()[-300:]


def ground_truth_of(capture: str | Path) -> Path | None:
    """A `make-scene` dataset's folder when the capture is one (scene.json and gt/ beside it)."""
    path = Path(capture)
    folder = path if path.is_dir() else path.parent
    return folder if (folder / DatasetDir.INFO).is_file() and (folder / DatasetDir.GT).is_dir() else None


def fit_options(spec: RunSpec, fit_args: list[str]) -> list[str]:
    """The options of the run's `fit` after its capture and folder: the batch's, the capture's own,
    its seed and its preset."""
    seeds = [option for key in SEED_KEYS for option in ("--set", f"{key}={spec.seed}")]
    return [*fit_args, *spec.args, *seeds, *(["--preset", spec.preset] if spec.preset else [])]


def _config_options() -> argparse.ArgumentParser:
    """The fit options that make its config (those of `vq_mitsuba.cli.common`), the others left aside."""
    p = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    p.add_argument("--preset")
    p.add_argument("--config")
    p.add_argument("--set", action="append", default=[])
    for option in ("--downscale", "--max-size", "--background-color", "--holdout"):
        p.add_argument(option)
    return p


def asked_config(spec: RunSpec, fit_args: list[str]):
    """The config the run's `fit` would start a new run with (defaults <- preset <- --config <- the
    capture options <- each --set); None when its options do not make one (the fit will say why)."""
    from vq_mitsuba.config import load_config

    try:
        args, _ = _config_options().parse_known_args(fit_options(spec, fit_args))
    except (SystemExit, argparse.ArgumentError):
        return None
    flags = [f"capture.{key}={getattr(args, key)}" for key in ("downscale", "max_size", "background_color", "holdout")
             if getattr(args, key) is not None]
    try:
        return load_config(args.config, flags + args.set, preset=args.preset)
    except UserError:
        return None


def own_config(run: RunDir):
    """The run's own config (its config.yaml, which it has from the start of its material fit); None
    without one, or when it cannot be read (the fit will say why)."""
    try:
        return run.config() if run.saved_config() is not None else None
    except UserError:
        return None


def _shown(value) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def changed_settings(own, asked) -> list[str]:
    """`key=<the run's value> (asked <value>)` for each key whose value differs, in the config's order."""
    from vq_mitsuba.config import flat_keys, to_dict

    mine, theirs = flat_keys(to_dict(own)), flat_keys(to_dict(asked))
    keys = list(mine) + [k for k in theirs if k not in mine]
    return [f"{k}={_shown(mine.get(k))} (asked {_shown(theirs.get(k))})" for k in keys if mine.get(k) != theirs.get(k)]


def settings_digest(cfg) -> str:
    """Eight hex digits of the config without its seeds: runs that share them have the same settings."""
    from vq_mitsuba.config import flat_keys, to_dict

    flat = {k: v for k, v in flat_keys(to_dict(cfg)).items() if k not in SEED_KEYS}
    return hashlib.sha256(json.dumps(flat, sort_keys=True, default=str).encode()).hexdigest()[:8]


def refuse_changed_settings(out: Path, specs: list[RunSpec], fit_args: list[str], status: dict) -> set[str]:
    """Mark `refused` (in `status`) every run whose config.yaml differs from what this call asks for,
    naming the keys: a run goes on only with its own settings. Returns their names."""
    refused = set()
    for spec in specs:
        own = own_config(RunDir(out / spec.name))
        asked = asked_config(spec, fit_args) if own is not None else None
        changes = changed_settings(own, asked) if asked is not None else []
        if not changes:
            continue
        more = f" and {len(changes) - 4} more" if len(changes) > 4 else ""
        status[spec.name] = {**status.get(spec.name, {}), "status": REFUSED, "message": (
            f"its settings differ from this call's: {', '.join(changes[:4])}{more}; the run is left as it is: "
            "rerun with its own settings, or fit the new ones into another -o")}
        refused.add(spec.name)
    return refused


def this_node() -> str:
    """The Ray node a task runs on, as its IP address and the start of its id ('' outside Ray)."""
    try:
        import ray

        if not ray.is_initialized():
            return ""
        return f"{ray.util.get_node_ip_address()}/{ray.get_runtime_context().get_node_id()[:8]}"
    except Exception:  # noqa: BLE001 - a name to show, nothing depends on it
        return ""


def _wait_while_locked(run: Path, log: io.TextIOBase) -> None:
    """Wait (LOCK_WAIT_S at most) while another process holds the run: above all the fit of an earlier
    try, whose worker or node was lost, writing its checkpoint on its way out."""
    try:
        import fcntl
    except ImportError:
        return
    deadline, said = time.monotonic() + LOCK_WAIT_S, False
    while time.monotonic() < deadline:
        try:
            fd = os.open(run / RunDir.LOCK, os.O_RDONLY)
        except OSError:
            return  # no lock file: nobody holds the run
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if not said:
                log.write(f"# {run.name} is held by another process (an earlier try ending?); waiting for it\n")
                log.flush()
                said = True
        finally:
            os.close(fd)
        time.sleep(1.0)


def _earlier_tries(log_path: Path, call: str) -> list[str]:
    """The nodes of the earlier tries of this run in this batch call (its log's try lines)."""
    mark = f"# batch {call}: try on "
    try:
        return [line[len(mark):].strip() for line in log_path.read_text().splitlines() if line.startswith(mark)]
    except OSError:
        return []


def _retry_note(run: RunDir, node: str, earlier: list[str]) -> str:
    """What happened to a run that needed more than one try: where they ran, and the step it resumed from."""
    fit = run.fit_summary()
    resumed = fit.get("iterations", 0) - fit.get("steps_this_call", 0)
    tries = "try" if len(earlier) == 1 else "tries"
    return (f"retried: {len(earlier)} earlier {tries} lost (on {', '.join(earlier)}); finished on {node or 'a node'}"
            + (f", resumed from its checkpoint at step {resumed}" if resumed > 0 else ""))


def run_one(spec: RunSpec, out: str, fit_args: list[str], threads: int, evaluate: bool,
            eval_args: list[str] = (), call: str = "") -> dict:
    """One run (a Ray task's body): fit (resuming what the folder holds), then eval when asked. Each
    try writes the node it runs on into the run's log, so that a retry (`call`: this batch call)
    can say which tries before it were lost."""
    start = time.time()
    run = Path(out) / spec.name
    log_path = Path(out) / LOGS / f"{spec.name}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    earlier, node = _earlier_tries(log_path, call), this_node()
    with open(log_path, "a") as log:
        log.write(f"# batch {call}: try on {node or 'this machine'}\n")
        log.flush()
        _wait_while_locked(run, log)
        argv = ["fit", spec.capture, "-o", str(run), "--quiet", "--threads", str(threads),
                *fit_options(spec, fit_args)]
        if RunDir(run).holds_run_files():  # an interrupted run: its poses, geometry and checkpoint go on
            argv.append("--resume")
        code, message = _command(argv, log)
        row = {"status": "done" if code == 0 else "failed", "message": "" if code == 0 else message}
        if code == 0 and evaluate:
            gt = ground_truth_of(spec.capture)
            code, message = _command(["eval", str(run), "--quiet", "--threads", str(threads), *eval_args]
                                     + (["--gt", str(gt)] if gt else []), log)
            if code != 0:
                row = {"status": "eval failed", "message": message}
    if earlier and row["status"] == "done":
        row["message"] = _retry_note(RunDir(run), node, earlier)
    return {**row, "wall_s": round(time.time() - start, 1), "node": node, "tries": len(earlier) + 1,
            "nodes": [*earlier, node]}


def preview_camera(run: RunDir):
    """The view a run is shown by in the summary, in the run's world: its first held-out view
    (fit --holdout), else the first test view of the capture, else its first training view."""
    from vq_mitsuba.data.cameras import convert_world
    from vq_mitsuba.eval.evaluate import held_out_capture

    if run.config().capture.holdout > 0:
        held = held_out_capture(run)
        if held.cameras:
            return convert_world(held.cameras[0], held.world, run.info()["world"])
    views = run.cameras()
    return (views.get("test") or views["train"])[0]


def write_preview(run: RunDir, png: Path) -> None:
    """A small render of `preview_camera` under the fitted light (straight sRGB with alpha)."""
    from vq_mitsuba.render.views import Renderer, write_rgb_png

    cam = preview_camera(run)
    scale = min(1.0, VIEW_SIZE / max(cam.width, cam.height))
    cam = cam.scaled(max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))
    images = Renderer(run.load()).render(cam, spp=VIEW_SPP)
    png.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(png, lambda tmp: write_rgb_png(tmp, images))


def write_previews(out: Path, specs: list[RunSpec], status: dict) -> None:
    """OUT/views/<run>.png of every finished run that has none yet; a run that cannot be shown gets
    its reason in the summary's message instead."""
    from vq_mitsuba import messages

    todo = [s for s in specs if status.get(s.name, {}).get("status") == "done"
            and not (out / VIEWS / f"{s.name}.png").is_file()]
    for spec in messages.progress(todo, desc="views", unit="run", disable=not todo):
        try:
            write_preview(RunDir(out / spec.name), out / VIEWS / f"{spec.name}.png")
        except UserError as exc:
            status[spec.name]["message"] = f"no view: {exc}"


def figures(run: RunDir) -> dict:
    """A run's own settings (its train.iterations and `settings_digest`) and a finished run's headline
    figures, read through RunDir (missing ones left out)."""
    out = {}
    own = own_config(run)
    if own is not None:
        out.update(train_iterations=own.train.iterations, settings=settings_digest(own))
    fit = run.fit_summary() if run.dir.is_dir() else {}
    for key in ("iterations", "seconds", "final_psnr_train_batch"):
        if key in fit:
            out[key] = fit[key]
    materials = run.materials() if run.is_run() else None
    if materials is not None:
        out["materials"] = materials.get("num_materials")
    metrics = run.metrics()
    if metrics is not None:
        for key in ("novel_view", brdf.BASECOLOR):  # the view's and the albedo's headline PSNR
            value = metrics.get(key, {}).get("psnr") if isinstance(metrics.get(key), dict) else None
            if value is not None:
                out[f"{key}_psnr"] = value
    return out


COLUMNS = ["run", "capture", "preset", "seed", "train_iterations", "settings", "status", "message", "wall_s",
           "node", "tries", "iterations", "seconds", "final_psnr_train_batch", "materials", "novel_view_psnr",
           "basecolor_psnr"]


def write_summary(out: Path, specs: list[RunSpec], status: dict) -> None:
    """OUT/summary.csv and OUT/summary.md: one row per run, in the plan's order."""
    rows = []
    for spec in specs:
        record = status.get(spec.name, {"status": "not run"})
        rows.append({"run": spec.name, "capture": spec.capture, "preset": spec.preset or "", "seed": spec.seed,
                     **{k: record.get(k, "") for k in ("status", "message", "wall_s", "node", "tries")},
                     **figures(RunDir(out / spec.name))})
    text = io.StringIO()
    writer = csv.DictWriter(text, COLUMNS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out / "summary.csv", lambda tmp: tmp.write_text(text.getvalue()))

    def cell(row, key, fmt="{:.2f}"):
        value = row.get(key, "")
        return fmt.format(value) if isinstance(value, float) else str(value).replace("|", "/").replace("\n", " ")

    done = sum(r["status"] == "done" for r in rows)
    nodes = sorted({n for r in rows for n in (status.get(r["run"], {}).get("nodes") or [r.get("node")]) if n})
    retried = [r["run"] for r in rows if isinstance(r.get("tries"), int) and r["tries"] > 1]
    lines = [f"# Batch: {done} of {len(rows)} runs done", ""]
    if nodes:
        lines += [f"Ray nodes the runs ran on: {', '.join(nodes)}; " + (
            f"{len(retried)} run{'s' if len(retried) > 1 else ''} needed more than one try, the earlier ones lost "
            f"with their worker or node ({', '.join(retried)}: see the status)." if retried
            else "no run needed a second try."), ""]
    lines += ["Iterations: the steps a run did of its own train.iterations; settings: a digest of its config.yaml "
              "without the seeds (runs that share it were fitted with the same settings).", "",
              "| run | status | iterations | settings | M | novel view PSNR | basecolor PSNR | fit s | node "
              "| a novel view | material sheet |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]

    def picture(path: Path) -> str:
        return f'<img src="{path}" width="200">' if (out / path).is_file() else ""

    def iterations(row) -> str:
        if row.get("train_iterations", "") == "":
            return cell(row, "iterations")
        return f"{row.get('iterations', '-')} of {row['train_iterations']}"

    for row in rows:
        status = row["status"] + (f": {cell(row, 'message')}" if row.get("message") else "")
        lines.append(f"| {row['run']} | {status} | {iterations(row)} | {cell(row, 'settings')} | "
                     f"{cell(row, 'materials')} | {cell(row, 'novel_view_psnr')} | "
                     f"{cell(row, 'basecolor_psnr')} | {cell(row, 'seconds', '{:.0f}')} | {cell(row, 'node')} | "
                     f"{picture(Path(VIEWS) / (row['run'] + '.png'))} | {picture(Path(row['run']) / RunDir.SHEET)} |")
    write_atomic(out / "summary.md", lambda tmp: tmp.write_text("\n".join(lines) + "\n"))


def check_output(out: Path) -> dict:
    """OUT is new, empty, or a batch folder (batch.json): its record of finished runs."""
    check_output_folder(out, "batch", "batch")
    if (out / STATUS).is_file():
        runs = read_json(out / STATUS, "").get("runs")
        if not isinstance(runs, dict):
            raise InputError(out / STATUS, "expected {\"runs\": {...}}: not a batch record")
        return runs
    return {}


def _start_ray(address: str | None, cpus: int | None, threads: int):
    """Ray, joined at `address` or started on this machine's cores; the command's SIGINT and SIGTERM
    handlers are kept (ray.init installs its own, which end the process with a stack dump)."""
    import ray

    from vq_mitsuba.backend import own_signal_handlers

    if ray.is_initialized():
        return ray, False
    cores = cpus or os.cpu_count() or 1
    if not address and threads > cores:
        raise InputError(None, f"--threads-per-run {threads}: this machine has {cores} cores, so no run could "
                               f"ever start; use at most {cores} (or --address to join a cluster)")
    try:
        with own_signal_handlers():
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False,
                         object_store_memory=80 * 1024 ** 2)
    except (ConnectionError, ValueError, RuntimeError, TimeoutError) as exc:
        ray.shutdown()
        what = f"--address {address}" if address else "Ray on this machine"
        first = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else type(exc).__name__
        raise InputError(None, f"{what}: Ray could not start or connect ({first})") from None
    return ray, True


# Run apart from the batch: when the batch's process is gone (kill -9 gives it no time to stop Ray),
# end the Ray processes it started on this machine.
_WATCHDOG = """
import os, sys, time
parent, pids = int(sys.argv[1]), [int(p) for p in sys.argv[2:]]
while os.getppid() == parent:
    time.sleep(1)
for pid in pids:
    try:
        os.kill(pid, 9)
    except OSError:
        pass
"""


def _descendants(pid: int) -> list[int]:
    """The processes started by `pid`, their children and so on (Linux /proc; none elsewhere)."""
    parent_of = {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else []:
        try:
            with open(f"/proc/{entry}/stat") as f:
                parent_of[int(entry)] = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            pass
    found, frontier = [], [pid]
    while frontier:
        children = [p for p, parent in parent_of.items() if parent in frontier]
        found += children
        frontier = children
    return found


def _watch_ray():
    """A watchdog process that ends the Ray processes this batch started (its children now) once the
    batch's process is gone; None where processes cannot be listed."""
    pids = _descendants(os.getpid())
    if not pids:
        return None
    return subprocess.Popen([sys.executable, "-c", _WATCHDOG, str(os.getpid()), *map(str, pids)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def run_batch(captures: list[str], out: str | Path, seeds: list[int] = (0,), presets: list[str | None] = (None,),
              fit_args: list[str] = (), threads: int = 1, evaluate: bool = False, address: str | None = None,
              cpus: int | None = None, capture_args: dict[str, list[str]] | None = None,
              eval_args: list[str] = ()) -> list[dict]:
    """Fit every planned run as a Ray task (skipping those OUT/batch.json records as done) and write
    the summary. `fit_args` go to every fit, `capture_args[capture]` to that capture's, `eval_args`
    to every eval. Returns the summary's rows as status records, in the plan's order."""
    out = Path(out)
    specs = plan(list(captures), list(seeds), list(presets), capture_args)
    status = check_output(out)
    refused = refuse_changed_settings(out, specs, list(fit_args), status)
    todo = [s for s in specs if s.name not in refused and (
            status.get(s.name, {}).get("status") != "done" or not (out / s.name / RunDir.FIT).is_file())]
    ray, started = _start_ray(address, cpus, threads)  # before OUT exists: a failed start leaves nothing
    watchdog = _watch_ray() if started and not address else None
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / STATUS, {"runs": status})  # the folder is the batch's from here: a rerun resumes it
        task = ray.remote(run_one).options(num_cpus=threads, max_retries=RETRIES, retry_exceptions=[RunLost])
        call = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"  # this call's tries in the runs' logs
        pending = {task.remote(s, str(out.resolve()), list(fit_args), threads, evaluate, list(eval_args), call): s
                   for s in todo}
        _gather(ray, pending, out, specs, status, skipped=len(specs) - len(todo))
    finally:
        if started:
            ray.shutdown()
        if watchdog is not None:
            watchdog.kill()
            watchdog.wait()
    write_previews(out, specs, status)
    write_summary(out, specs, status)
    return [{"run": s.name, **status.get(s.name, {})} for s in specs]


def _gather(ray, pending: dict, out: Path, specs: list[RunSpec], status: dict, skipped: int) -> None:
    from vq_mitsuba import messages

    bar = messages.progress(total=len(specs), initial=skipped, desc="batch", unit="run")
    failed = 0
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        spec = pending.pop(ready[0])
        try:
            record = ray.get(ready[0])
        except Exception as exc:  # retries spent, or Ray lost the task
            cause = exc.cause if isinstance(getattr(exc, "cause", None), Exception) else exc
            record = {"status": "failed", "message": f"{type(cause).__name__}: {cause}"}
        failed += record["status"] != "done"
        status[spec.name] = record
        write_json(out / STATUS, {"runs": status})
        bar.update(1)
        bar.set_postfix(running=len(pending), failed=failed)
    bar.close()


def parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(None, f"--seeds {text}: expected whole numbers separated by commas, e.g. 0,1,2") from None
    if not seeds or any(s < 0 or s > MAX_SEED for s in seeds) or len(set(seeds)) < len(seeds):
        raise InputError(None, f"--seeds {text}: expected distinct seeds from 0 to {MAX_SEED}, e.g. 0,1,2")
    return seeds
