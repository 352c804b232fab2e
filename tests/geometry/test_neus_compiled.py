"""NeuS's training step in the fixed-shape form `torch.compile` fuses (`NeuS.training_step`): the
same colour, opacity, eikonal term and parameter gradients as the eager step, whether it runs
eagerly or compiled, rays that miss the hull included; long stages compile it, short ones do not."""

import pytest
import torch

from test_geometry import small_cfg, sphere_capture
from vq_mitsuba.compiled import Compiled
from vq_mitsuba.geometry.neus import neus_for
from vq_mitsuba.geometry.neus import NeuSTraining, training


@pytest.fixture(scope="module")
def neus():
    model = neus_for(sphere_capture(n_views=6, size=16), small_cfg(iterations=1, batch_rays=96))
    with torch.no_grad():  # a model away from its start, so that every parameter gets a gradient
        gen = torch.Generator().manual_seed(3)
        for p in model.model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=gen))
    model.refresh_occupancy([1.0] * model.cfg.levels)
    return model


def _batch(neus):
    gen = torch.Generator().manual_seed(1)
    idx = torch.randint(0, len(neus.rays_o), (neus.cfg.batch_rays,), generator=gen)
    o, d = neus.rays_o[idx].clone(), neus.rays_d[idx].clone()
    o[:8], d[:8] = torch.tensor([2.0, 2.0, 2.0]), torch.tensor([0.0, 0.0, 1.0])  # rays that miss the hull
    near, far = neus.intervals(o, d)
    assert bool((far <= near + 1e-6)[:8].all()) and bool((far > near + 1e-6).sum() > 40)
    return o, d, near, far


def _step(neus, step_fn):
    """(rgb, acc, eikonal, every parameter's gradient) of one loss through the step."""
    neus.compiled_step = step_fn
    o, d, near, far = _batch(neus)
    neus.model.zero_grad(set_to_none=True)
    torch.manual_seed(7)  # the samples' jitter
    out = neus.render(o, d, [1.0, 0.8, 0.3], neus.cfg.n_samples, True, True, near=near, far=far)
    loss = out["rgb"].square().mean() + out["acc"].mean() + 0.1 * out["eikonal"]
    loss.backward()
    grads = {n: p.grad.clone() for n, p in neus.model.named_parameters() if p.grad is not None}
    neus.compiled_step = None
    return out["rgb"].detach(), out["acc"].detach(), out["eikonal"].detach(), grads


def _assert_same(a, b, tol):
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(x, y, rtol=tol, atol=tol)
    assert set(a[3]) == set(b[3]) and len(a[3]) >= 8
    for name in a[3]:
        torch.testing.assert_close(a[3][name], b[3][name], rtol=tol, atol=tol, msg=name)


def test_the_fixed_shape_step_gives_the_eager_values_and_gradients(neus):
    eager = _step(neus, None)
    assert float(eager[1][:8].abs().max()) == 0.0 and float(eager[1].max()) > 0.1
    assert any(float(g.abs().max()) > 0 for g in eager[3].values())
    _assert_same(_step(neus, neus.training_step), eager, 1e-5)


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_the_compiled_step_gives_the_eager_values_and_gradients(neus, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    monkeypatch.delenv("TORCH_COMPILE_DISABLE", raising=False)
    eager = _step(neus, None)
    compiled = Compiled(neus.training_step, "NeuS's step", data_dependent_shapes=True)
    first = _step(neus, compiled)
    assert compiled.state == "compiled", compiled.reason
    _assert_same(first, eager, 1e-4)
    _assert_same(_step(neus, compiled), eager, 1e-4)  # the second call replays the compiled code


def test_a_long_stage_compiles_its_step_and_a_short_one_does_not(monkeypatch):
    seen = []
    monkeypatch.setattr(training, "Compiled", lambda fn, name, **kw: seen.append(name) or None)
    for steps in (training.COMPILE_FROM - 1, training.COMPILE_FROM):
        fit = NeuSTraining(neus_for(sphere_capture(n_views=4, size=12), small_cfg(iterations=steps)), None)
        fit.plan_compile()
        seen.append(steps)
    assert seen == [training.COMPILE_FROM - 1, "NeuS's step", training.COMPILE_FROM]


def test_the_neus_model_imports_no_capture_code():
    """The model's module (renderer: box, occupancy, volume rendering of rays) and everything it
    imports from the package, at any depth, import nothing from vq_mitsuba.data: a capture reaches
    NeuS only through `rays.neus_for`."""
    import ast
    from pathlib import Path

    package = Path(training.__file__).resolve().parents[2]

    def imports(module: str) -> set[str]:
        path = package.parent / (module.replace(".", "/") + ".py")
        if not path.is_file():
            path = path.with_suffix("") / "__init__.py"
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("vq_mitsuba"):
                found |= {f"{node.module}.{a.name}" if (package.parent / node.module.replace(".", "/")).is_dir()
                          and (package.parent / node.module.replace(".", "/") / f"{a.name}.py").is_file()
                          else node.module for a in node.names}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name.startswith("vq_mitsuba")}
        return found

    seen, todo = set(), ["vq_mitsuba.geometry.neus.renderer"]
    while todo:
        module = todo.pop()
        if module not in seen:
            seen.add(module)
            todo += sorted(imports(module) - seen)
    assert "vq_mitsuba.geometry.neus.networks" in seen and "vq_mitsuba.config" in seen
    assert not [m for m in seen if m.startswith("vq_mitsuba.data")], sorted(seen)
    assert "vq_mitsuba.data.cameras" in imports("vq_mitsuba.geometry.neus.rays")  # the check can fail
