"""The Mitsuba variant and the torch device, chosen once for the whole process."""

from __future__ import annotations

import os
from contextlib import contextmanager

import mitsuba as mi
import torch

_VARIANT_READY = False
DEVICES = ("auto", "cpu", "cuda")
_REQUESTED = "auto"  # the --device the process was started with (choose_device)


def _cuda_problems(both: bool = False) -> list[str]:
    """What keeps this process off the GPU: empty when torch's CUDA works and Mitsuba's
    `cuda_ad_rgb` variant can be set (it is left set then); `both`: Mitsuba is tried also when
    torch has no CUDA, so that the answer names every missing half."""
    problems = []
    if not torch.cuda.is_available():
        problems.append("torch sees no CUDA device (a CPU build of torch, or no GPU driver)")
    if both or not problems:
        try:
            mi.set_variant("cuda_ad_rgb")
        except Exception as exc:  # no usable CUDA driver for Dr.Jit, or a build without the variant
            why = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            problems.append(f"Mitsuba cannot set cuda_ad_rgb ({why})")
    return problems


def choose_device(name: str = "auto") -> str:
    """Choose the one device of the process, once: "cuda" when `name` is auto and both Mitsuba's
    `cuda_ad_rgb` and torch's CUDA work (InputError when `name` is cuda and either does not), else
    "cpu" (`llvm_ad_rgb` and torch's CPU, also on a GPU machine). Returns the device chosen."""
    global _VARIANT_READY, _REQUESTED
    from vq_mitsuba.errors import InputError

    if name not in DEVICES:
        raise InputError(None, f"--device {name}: expected one of {', '.join(DEVICES)}")
    problems = _cuda_problems(both=name == "cuda") if name != "cpu" else ["--device cpu"]
    variant = "llvm_ad_rgb" if problems else "cuda_ad_rgb"
    if mi.variant() != variant:
        mi.set_variant(variant)
    if name == "cuda" and problems:
        raise InputError(None, "--device cuda: " + "; ".join(problems) + " (--device auto or cpu runs on the CPU)")
    _VARIANT_READY, _REQUESTED = True, name
    return "cpu" if problems else "cuda"


def init_mitsuba(variant: str | None = None) -> str:
    """The Mitsuba variant of the process: the chosen device's (`choose_device`, auto when no
    device was chosen yet), or `variant` when one is named; returns it."""
    global _VARIANT_READY
    if variant is not None:
        if mi.variant() != variant:
            mi.set_variant(variant)
        _VARIANT_READY = True
    elif not _VARIANT_READY:
        choose_device("auto")
    return mi.variant()


def torch_device() -> torch.device:
    """The torch device matching the Mitsuba variant (tensors cross `dr.wrap` without copies); the
    one answer every module asks. Without a variant set yet, the device is chosen first (auto)."""
    if mi.variant() is None:
        init_mitsuba()
    return torch.device("cuda") if mi.variant().startswith("cuda") else torch.device("cpu")


# A step's work on a GPU, as a multiple of the CPU's: one unit per UNIT_SMS multiprocessors, at most
# MAX_SCALE units, and no more units than the device's memory holds at UNIT_MEMORY bytes each.
UNIT_SMS, MAX_SCALE, UNIT_MEMORY = 16, 8, 8 << 30


def device_scale() -> int:
    """How many times the CPU's batch one step takes on the process's device: 1 on the CPU; on a GPU
    one unit per 16 multiprocessors, at most 8, and at most one per 8 GiB of its memory."""
    device = torch_device()
    if device.type != "cuda":
        return 1
    props = torch.cuda.get_device_properties(device)
    return max(1, min(MAX_SCALE, props.multi_processor_count // UNIT_SMS, props.total_memory // UNIT_MEMORY))


def sized(value: int, cpu_value: int) -> int:
    """A size setting resolved: `value` when given (> 0), else `cpu_value` times `device_scale()`."""
    return int(value) if value > 0 else int(cpu_value) * device_scale()


def device_record() -> dict:
    """What run.json records of the device: requested (--device), used (cpu or cuda), the Mitsuba
    variant and torch's name of the device."""
    device = torch_device()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    return {"requested": _REQUESTED, "used": device.type, "variant": mi.variant(), "torch_device": name}


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. under taskset or a container quota)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def max_threads() -> int:
    """The most threads `set_threads` takes: 4 per core of the machine (more only add switching,
    and thousands of them exhaust the stacks Dr.Jit's pool allocates)."""
    return 4 * max(1, os.cpu_count() or 1)


def set_threads(n: int | None = None) -> int:
    """Use n CPU threads (default: the available cores) in torch and in Dr.Jit's LLVM backend.

    OpenMP's worker threads wait passively (OMP_WAIT_POLICY=PASSIVE, set when vq_mitsuba is
    imported first): spinning threads would fight a busy neighbour process for the same cores."""
    import drjit as dr

    from vq_mitsuba.errors import InputError

    most = max_threads()
    if n is not None and not 0 <= int(n) <= most:
        raise InputError(None, f"--threads {n}: expected 1 to {most} (4 per core of the {os.cpu_count() or 1} "
                               "this machine has)")
    n = available_cores() if not n else int(n)
    torch.set_num_threads(n)
    # Mitsuba reads EXR files with nested tasks on Dr.Jit's pool, which wait forever on a pool of
    # one worker: Dr.Jit gets two threads at least (the second sleeps while the first computes).
    dr.set_thread_count(max(n, 2))
    return n


class shading_threads:
    """Within the block, torch uses half its CPU threads (at least one) while Dr.Jit shades beside
    it: in a training step Dr.Jit's LLVM kernels run asynchronously on its own pool of every core,
    next to torch's operations, and a second pool of every core for torch makes them fight over the
    cores (on 2 cores a material step took 1.5-2x as long; rendering, whose torch work waits for the
    kernels, was 1.25x slower with half: it keeps every thread; benchmarks/results/compiled/).
    Nothing changes on a GPU. torch's count is the calling thread's own (OpenMP's), so blocks in
    several threads (the editor's server) do not touch each other's; leaving restores the count the
    block found."""

    def __enter__(self):
        self.old = torch.get_num_threads()
        if torch_device().type == "cpu":
            torch.set_num_threads(max(1, self.old // 2))
        return self

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)
        return False


@contextmanager
def own_signal_handlers():
    """The process's SIGINT and SIGTERM handlers as they were before the block, whatever a library
    installed inside it: pycolmap's glog and ray.init put in handlers that print a stack dump and
    kill the process, in place of a command's (which checkpoint, release the run's lock and exit
    130 / 143). Only the main thread sets handlers; elsewhere nothing changes."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)} if main else {}
    try:
        yield
    finally:
        for sig, handler in before.items():
            if handler is not None:
                signal.signal(sig, handler)


def import_pycolmap():
    """pycolmap, imported without letting its glog take the process's signals (`own_signal_handlers`)."""
    with own_signal_handlers():
        import pycolmap
    return pycolmap


def available_memory() -> int:
    """Bytes a computation may still take: the GPU's free memory when torch runs on one, else the
    machine's available memory (/proc/meminfo's MemAvailable; 0 where unknown)."""
    device = torch_device()
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0
