"""One device for a process: NeuS puts its model, training rays and grids on `backend.torch_device()`,
every tensor NeuS creates names its device, and a step waits for the device only when the losses
are read (every HISTORY_EVERY steps)."""

import ast
from pathlib import Path

import pytest
import torch

from vq_mitsuba import backend
from vq_mitsuba.backend import choose_device, torch_device
from vq_mitsuba.geometry.neus import neus_for
from vq_mitsuba.geometry.neus import reconstruct, train
from vq_mitsuba.geometry.neus import training as neus_fit

from test_geometry import small_cfg, sphere_capture

NEUS = Path(__file__).resolve().parents[2] / "vq_mitsuba" / "geometry" / "neus"
FACTORIES = {"rand", "randn", "randint", "zeros", "ones", "empty", "full", "arange", "tensor", "linspace"}


@pytest.fixture
def cpu_device():
    """--device cpu for one test, then the process's own choice again (on a GPU machine: CUDA)."""
    import mitsuba as mi

    before = (mi.variant(), backend._REQUESTED)
    yield choose_device("cpu")
    if before[0] is not None and mi.variant() != before[0]:
        mi.set_variant(before[0])
    backend._REQUESTED = before[1]


def test_every_tensor_neus_creates_names_its_device():
    """torch.zeros(...) without device= lands on the CPU whatever the model's device: on a GPU that
    is a silent copy per step (or an error), so every factory call says where."""
    missing = []
    for path in sorted(NEUS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in FACTORIES
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"
                    and not any(k.arg == "device" for k in node.keywords)):
                missing.append(f"{path.name}:{node.lineno} torch.{node.func.attr}")
    assert not missing, missing


def test_neus_trains_on_the_chosen_cpu_device_and_reads_its_losses_every_ten_steps(cpu_device, monkeypatch):
    assert cpu_device == "cpu" and torch_device() == torch.device("cpu")
    reads = []
    read = neus_fit.NeuSTraining.read_history
    monkeypatch.setattr(neus_fit.NeuSTraining, "read_history",
                        lambda self: (reads.append(len(self.pending)), read(self))[1])
    neus = neus_for(sphere_capture(n_views=6, size=20), small_cfg(iterations=23))
    assert neus.device == torch.device("cpu")
    box = neus.box
    tensors = [neus.rays_o, neus.rays_d, neus.rays_rgb, neus.rays_alpha, box.hull, box.hull_dilated, box.hull_sdf]
    assert all(t.device == neus.device for t in tensors)
    assert all(p.device == neus.device for p in neus.model.parameters())
    summary = train(neus, None)
    history = summary["history"]
    assert [h["step"] for h in history] == list(range(1, 24))
    assert set(history[0]) == {"step", "seconds", "loss", "color", "eikonal", "mask", "psnr", "s", "points"}
    assert all(isinstance(v, float) for h in history for k, v in h.items() if k != "step")
    assert [n for n in reads if n] == [10, 10, 3]  # the losses read in batches, the tail at the end


def test_a_neus_checkpoint_of_the_other_device_kind_resumes(cpu_device, tmp_path):
    """A checkpoint is read onto the CPU and copied to the model's device; a random generator of the
    other kind (CUDA's Philox state on a CPU, or the reverse) cannot continue, and a new stream starts."""
    capture = sphere_capture(n_views=6, size=20)
    reconstruct(capture, tmp_path, small_cfg(iterations=3, checkpoint_every=3))
    state = torch.load(tmp_path / "neus.pt", weights_only=False)
    state["generator"] = torch.zeros(16, dtype=torch.uint8)  # the size of a CUDA generator's state
    torch.save(state, tmp_path / "neus.pt")
    again = reconstruct(capture, tmp_path, small_cfg(iterations=5), resume=True)
    assert again.summary["iterations"] == 5
    assert len(torch.load(tmp_path / "neus.pt", weights_only=False)["history"]) == 5
    record = again.summary["device"]
    assert record == {"requested": "cpu", "used": "cpu", "variant": "llvm_ad_rgb", "torch_device": "cpu"}


class _Card:
    def __init__(self, sms: int, gib: int):
        self.multi_processor_count, self.total_memory = sms, gib << 30


@pytest.mark.parametrize("sms, gib, scale", [(132, 80, 8), (132, 141, 8), (108, 40, 5), (46, 16, 2), (20, 8, 1),
                                             (80, 12, 1)])
def test_a_gpu_step_takes_a_multiple_of_the_cpu_batch_by_its_multiprocessors_and_memory(monkeypatch, sms, gib,
                                                                                      scale):
    monkeypatch.setattr(backend, "torch_device", lambda: torch.device("cuda"))
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: _Card(sms, gib))
    assert backend.device_scale() == scale
    assert backend.sized(0, 512) == 512 * scale and backend.sized(300, 512) == 300  # a given size is kept


def test_sizes_left_at_auto_are_the_cpu_defaults_on_the_cpu(cpu_device):
    from vq_mitsuba.config import CPU_NEUS_BATCH, load_config
    from vq_mitsuba.geometry.neus.renderer import choose_iterations

    cfg = load_config(None)
    assert (cfg.neus.batch_rays, cfg.render.chunk) == (0, 0)  # auto
    assert backend.device_scale() == 1 and backend.sized(cfg.render.chunk, 65536) == 65536
    neus_cfg, info = choose_iterations(cfg.neus, 1_000_000)
    assert neus_cfg.batch_rays == info["batch_rays"] == CPU_NEUS_BATCH
    assert info["iterations"] == 0  # no step limit: the time budget and the plateau end training


def test_tests_that_build_cpu_inputs_skip_where_the_process_runs_on_a_gpu(monkeypatch):
    import conftest

    class Item:
        def __init__(self, marked: bool):
            self.marked = marked

        def get_closest_marker(self, name):
            return object() if self.marked and name == "cpu_inputs" else None

    monkeypatch.setattr(backend, "torch_device", lambda: torch.device("cuda"))
    with pytest.raises(pytest.skip.Exception, match="CPU tensors"):
        conftest.pytest_runtest_setup(Item(marked=True))
    conftest.pytest_runtest_setup(Item(marked=False))  # unmarked: runs on a GPU too
    monkeypatch.setattr(backend, "torch_device", lambda: torch.device("cpu"))
    conftest.pytest_runtest_setup(Item(marked=True))  # on the CPU: runs


def test_torch_takes_half_the_threads_while_dr_jit_shades_beside_it_and_gets_them_back(cpu_device):
    """`backend.shading_threads`: on the CPU, torch's pool shrinks to half (at least one thread) in the
    block, so that Dr.Jit's kernels and torch's operations do not both claim every core; the count
    comes back on leaving, also when the block raises."""
    before = torch.get_num_threads()
    try:
        for threads, inside in ((4, 2), (2, 1), (1, 1)):
            torch.set_num_threads(threads)
            with backend.shading_threads():
                assert torch.get_num_threads() == inside
            assert torch.get_num_threads() == threads
        torch.set_num_threads(2)
        with pytest.raises(RuntimeError), backend.shading_threads():
            raise RuntimeError("a failed step")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_shading_blocks_nest_and_one_in_another_thread_leaves_this_threads_count(cpu_device):
    """Nested blocks restore the count each found; a block in another thread (the editor's server
    renders in its own) halves that thread's count, not this one's."""
    import threading

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(4)
        with backend.shading_threads():
            with backend.shading_threads():
                assert torch.get_num_threads() == 1
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 4
        inside, leave, seen = threading.Event(), threading.Event(), []

        def other():
            torch.set_num_threads(2)
            with backend.shading_threads():
                seen.append(torch.get_num_threads())
                inside.set()
                leave.wait(5)
            seen.append(torch.get_num_threads())

        worker = threading.Thread(target=other)
        worker.start()
        assert inside.wait(5)
        assert torch.get_num_threads() == 4
        leave.set()
        worker.join(5)
        assert seen == [1, 2] and torch.get_num_threads() == 4
    finally:
        torch.set_num_threads(before)
