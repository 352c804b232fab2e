"""Loss functions against hand-computed values and their defining properties (vq_mitsuba.models.losses)."""

import math

import pytest
import torch

from vq_mitsuba.models import losses


def test_lambertian_prior_value_and_gradients_with_metallic_weight():
    m = torch.tensor([0.2, 0.6, 1.0], requires_grad=True)
    r = torch.tensor([0.1, 0.5, 0.9], requires_grad=True)
    loss = losses.lambertian_prior(m, r, metallic_weight=10.0)
    assert math.isclose(float(loss.detach()), 10.0 * 0.6 + (1.0 - 0.5), rel_tol=1e-6)
    loss.backward()
    assert torch.allclose(m.grad, torch.full((3,), 10.0 / 3))  # pulls metallic down, 10x harder
    assert torch.allclose(r.grad, torch.full((3,), -1.0 / 3))  # pulls roughness up
    # The paper's form is the default: both terms weighed equally.
    assert math.isclose(float(losses.lambertian_prior(m, r).detach()), 0.6 + 0.5, rel_tol=1e-6)


def test_decorrelated_l2_has_no_variance_bias():
    """E[plain L2 of a noisy estimate] = bias^2 + variance; the decorrelated form keeps bias^2 only,
    so a noisy but unbiased estimator is not penalised against a noise-free one."""
    g = torch.Generator().manual_seed(0)
    target = torch.full((20000, 3), 0.25)
    # Unbiased in the encoded space is what the loss compares; build samples around the target's code.
    noisy = target[:, None, :] * torch.exp(0.5 * torch.randn(20000, 8, 3, generator=g) - 0.125)  # mean = target
    plain = losses.reconstruction_l2(noisy.mean(1), target, gamma=1.0)
    decor = losses.reconstruction_l2_decorrelated(noisy, target, gamma=1.0)
    assert float(plain) > 20 * abs(float(decor))
    assert abs(float(decor)) < 2e-4
    # A biased estimate keeps its squared bias.
    shifted = noisy + 0.05
    assert math.isclose(float(losses.reconstruction_l2_decorrelated(shifted, target, gamma=1.0)), 0.05**2, rel_tol=0.2)


def test_chromaticity_loss_ignores_intensity_but_not_hue():
    c = torch.tensor([[0.6, 0.3, 0.1], [0.2, 0.2, 0.2]])
    assert float(losses.chromaticity_loss(3.0 * c, c)) < 1e-6
    assert float(losses.chromaticity_loss(c.flip(-1), c)) > 1e-2


def test_metallic_agreement_moves_only_the_discrete_metallic_to_the_median():
    """The term is the (weighted) mean absolute difference, zero where the branches agree; its
    gradient reaches the discrete metallic alone, and one value shared by many points (a
    codeword) is pulled to their median, not their mean."""
    m_c = torch.tensor([0.0, 0.9, 0.5], requires_grad=True)
    m_d = torch.tensor([0.4, 0.9, 0.3], requires_grad=True)
    loss = losses.metallic_agreement(m_d, m_c)
    assert math.isclose(float(loss), (0.4 + 0.0 + 0.2) / 3, rel_tol=1e-5)
    loss.backward()
    assert m_c.grad is None or float(m_c.grad.abs().sum()) == 0.0
    assert torch.allclose(m_d.grad, torch.tensor([1.0, 0.0, -1.0]) / 3)
    weighted = losses.metallic_agreement(m_d.detach(), m_c.detach(), torch.tensor([0.0, 1.0, 3.0]))
    assert math.isclose(float(weighted), 3.0 * 0.2 / 3, rel_tol=1e-5)
    # one codeword over eight points, two of them mixed edge points of a metal
    targets = torch.tensor([0.0, 0.01, 0.02, 0.0, 0.01, 0.0, 0.9, 0.8])
    code = torch.tensor(0.5, requires_grad=True)
    opt = torch.optim.SGD([code], lr=0.01)
    for _ in range(300):
        opt.zero_grad()
        losses.metallic_agreement(code.expand(8), targets).backward()
        opt.step()
    assert float(code) < 0.03 < float(targets.mean())


def test_colour_aware_smoothness_switches_off_across_colour_edges():
    a = {"basecolor": torch.tensor([[0.2, 0.4, 0.6]]), "metallic": torch.tensor([0.0]), "roughness": torch.tensor([0.5])}
    b = {"basecolor": torch.tensor([[0.4, 0.4, 0.6]]), "metallic": torch.tensor([1.0]), "roughness": torch.tensor([0.5])}
    same = torch.tensor([[0.3, 0.3, 0.3]])
    expected = (0.2 / 3) + 0.1 * 1.0  # basecolor mean |diff| + beta * |metallic diff|
    got = losses.colour_aware_smoothness(a, b, same, same, alpha=60.0, beta=0.1)
    assert math.isclose(float(got), expected, rel_tol=1e-5)
    edge = losses.colour_aware_smoothness(a, b, same, same + 0.1, alpha=60.0, beta=0.1)
    assert math.isclose(float(edge), expected * math.exp(-6.0), rel_tol=1e-4)



def test_metallic_barrier_is_minus_log_one_minus_metallic_and_keeps_pulling_at_saturation():
    logit = torch.tensor([-5.0, 0.0, 2.0, 12.0], requires_grad=True)
    m = torch.sigmoid(logit)
    rough = torch.full((4,), 0.5)
    barrier = losses.lambertian_prior(m, rough, 2.0, metallic_logit=logit)
    expected = 2.0 * torch.mean(-torch.log(torch.sigmoid(-logit.detach().double()))).float() + 0.5  # 1 - m = sigmoid(-logit)
    assert torch.allclose(barrier, expected, rtol=1e-4)
    (g_barrier,) = torch.autograd.grad(barrier, logit)
    (g_linear,) = torch.autograd.grad(losses.lambertian_prior(torch.sigmoid(logit), rough, 2.0), logit)
    # d/dlogit of weight * softplus / n is weight * metallic / n: the full weight at saturation,
    # where the linear term's sigmoid slope has all but vanished.
    assert torch.allclose(g_barrier, 2.0 * m.detach() / 4, rtol=1e-5)
    assert float(g_barrier[3]) > 0.49 and float(g_linear[3]) < 1e-5
    # Near metallic 0 the two agree to first order.
    assert abs(float(g_barrier[0]) - float(g_linear[0])) < 0.05 * float(g_linear[0])


def test_every_declared_term_reads_a_weight_the_config_has():
    """Each term of losses.TERMS names config keys that exist and hold finite weights; a decaying
    weight is its key's value at the start and value times factor at the end."""
    import math

    from vq_mitsuba.config import load_config

    cfg = load_config(None, [])
    for name, term in losses.TERMS.items():
        assert term.name == name
        if term.fixed is None:
            assert math.isfinite(losses.config_value(cfg, term.weight)), name
        start, end = losses.weight_of(cfg, name, 0.0), losses.weight_of(cfg, name, 1.0)
        if term.decay is None:
            assert start == end
        else:
            factor = losses.config_value(cfg, term.decay)
            assert start == pytest.approx(losses.config_value(cfg, term.weight))
            assert end == pytest.approx(start * factor)
    with pytest.raises(KeyError, match="no declaration"):
        losses.weight_of(cfg, "undeclared", 0.5)
    terms = losses.weighted({"rec_c": torch.tensor(2.0), "sm": torch.tensor(3.0)}, cfg, 0.0)
    assert float(terms["rec_c"]) == pytest.approx(2.0 * cfg.loss.w_rec_c)
    assert float(terms["sm"]) == pytest.approx(3.0 * cfg.loss.w_sm)
