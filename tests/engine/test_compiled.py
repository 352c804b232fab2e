"""Hot loops compiled with torch.compile (`vq_mitsuba.compiled`): the same values and gradients as
the eager step, the compiled code kept in the user's cache folder, and a compiler failure answered
by the eager step after one warning."""

import warnings

import pytest
import torch

from vq_mitsuba.compiled import Compiled
from vq_mitsuba.errors import Notice
from vq_mitsuba.models import losses
from vq_mitsuba.models.residual import ResidualField, add_residual


def _residual_problem(seed: int = 0, n: int = 512):
    gen = torch.Generator().manual_seed(seed)
    field = ResidualField([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], scale=0.5, finest=64)
    with torch.no_grad():  # an output layer away from zero, so that every parameter gets a gradient
        field.mlp[-1].weight.normal_(0.0, 0.1, generator=gen)
    unit = lambda: torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)  # noqa: E731
    data = (torch.rand(n, 3, generator=gen), unit(), unit(), torch.rand(n, 3, generator=gen),
            torch.rand(n, 3, generator=gen))
    return field, data


def _gradients(field):
    def step(points, normals, wi, physical, target):
        field.zero_grad(set_to_none=True)
        loss = losses.reconstruction_l2(add_residual(physical, field(points, normals, wi)), target, 2.2)
        loss.backward()
        return loss
    return step


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_the_compiled_step_gives_the_eager_values_and_gradients_and_caches_in_the_user_folder(tmp_path,
                                                                                             monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    monkeypatch.delenv("TORCH_COMPILE_DISABLE", raising=False)
    field, data = _residual_problem()
    eager_loss = _gradients(field)(*data)
    eager_grads = [p.grad.clone() for p in field.parameters()]
    step = Compiled(_gradients(field), "test step")
    for _ in range(2):  # the second call replays the compiled code
        loss = step(*data)
    assert step.state == "compiled"
    assert torch.allclose(loss, eager_loss, rtol=1e-5, atol=1e-7)
    for p, want in zip(field.parameters(), eager_grads):
        assert torch.allclose(p.grad, want, rtol=1e-4, atol=1e-7), float((p.grad - want).abs().max())
    # some gradient is not zero, so the comparison compares something
    assert max(float(g.abs().max()) for g in eager_grads) > 1e-4
    cache = tmp_path / "cache" / "vq-mitsuba" / "torch" / "inductor"
    assert cache.is_dir() and any(f.is_file() for f in cache.rglob("*"))


def test_a_compiler_that_fails_leaves_the_eager_step_after_one_warning(monkeypatch):
    def broken(fn, **kwargs):
        def call(*args, **kw):
            raise RuntimeError("no C++ compiler\nsecond line")
        return call

    monkeypatch.setattr(torch, "compile", broken)
    field, data = _residual_problem(1)
    eager_loss = _gradients(field)(*data)
    eager_grads = [p.grad.clone() for p in field.parameters()]
    step = Compiled(_gradients(field), "test step")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        losses_seen = [step(*data) for _ in range(3)]
    notices = [w for w in caught if issubclass(w.category, Notice)]
    assert len(notices) == 1 and "test step" in str(notices[0].message) and "no C++ compiler" in str(
        notices[0].message)
    assert step.state == "eager"
    for loss in losses_seen:
        assert torch.allclose(loss, eager_loss, rtol=1e-6, atol=0.0)
    for p, want in zip(field.parameters(), eager_grads):  # the table's scatter adds in thread order
        assert torch.allclose(p.grad, want, rtol=1e-5, atol=1e-9)


def test_a_missing_cxx_compiler_falls_back_to_eager(tmp_path, monkeypatch):
    """A real compiler failure: Inductor pointed at a C++ compiler that does not exist, with an
    empty cache (nothing to load instead of compiling)."""
    inductor_config = pytest.importorskip("torch._inductor.config")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    torch._dynamo.reset()

    def f(x):
        return torch.sin(x) * 2.0 + x.square()

    x = torch.linspace(-1.0, 1.0, 17)
    step = Compiled(f, "test function")
    # the config's own patch: monkeypatch's undo would delete the key rather than restore it
    with inductor_config.patch({"cpp.cxx": (None, str(tmp_path / "no-such-c++"))}):
        with pytest.warns(Notice, match="test function: torch.compile failed"):
            out = step(x)
    assert step.state == "eager" and torch.equal(out, f(x))
    torch._dynamo.reset()
