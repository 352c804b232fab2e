"""Discrete branch pieces: straight-through gradients, EMA updates, ranking rule."""

import pytest
import torch
import torch.nn.functional as F

from vq_mitsuba.models.vq import (VectorQuantizerEMA, choose_num_materials, dropout_rates,
                                     sample_drop_mask, scale_gradient)


def test_straight_through_gradient_reaches_the_encoder():
    torch.manual_seed(0)
    encoder = torch.nn.Linear(3, 4)
    vq = VectorQuantizerEMA(5, 4)
    x = torch.randn(16, 3)
    z_q, idx, loss = vq(encoder(x))
    (z_q.sum() + loss).backward()
    assert encoder.weight.grad is not None and encoder.weight.grad.abs().sum() > 0
    # Forward value is the codeword (in eval mode the codebook does not move during the call).
    vq.eval()
    z_q2, idx2, _ = vq(encoder(x))
    torch.testing.assert_close(z_q2, vq.codebook[idx2])


def test_joint_scale_scales_the_discrete_gradient_reaching_the_encoder():
    torch.manual_seed(0)
    encoder = torch.nn.Linear(3, 4)
    vq = VectorQuantizerEMA(5, 4)
    vq.eval()  # the codebook stays put between the two passes
    x, w = torch.randn(16, 3), torch.randn(16, 4)

    def encoder_grad(scale):
        encoder.zero_grad()
        z = encoder(x)
        z_s = scale_gradient(z, scale)
        torch.testing.assert_close(z_s, z)  # the forward value does not change
        z_q, _, loss = vq(z_s)
        ((z_q * w).sum() + loss).backward()
        return encoder.weight.grad.clone()

    full = encoder_grad(1.0)
    assert full.abs().sum() > 0
    torch.testing.assert_close(encoder_grad(0.2), 0.2 * full)


def test_ema_update_matches_hand_computation():
    vq = VectorQuantizerEMA(2, 2, decay=0.5, eps=0.0, dead_after=1000)
    vq.init_codebook(torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    z = F.normalize(torch.tensor([[1.0, 0.2], [1.0, -0.2], [0.1, 1.0]]), dim=-1)
    idx = vq.nearest(z)
    assert idx.tolist() == [0, 0, 1]
    vq.ema_update(z, idx)
    # count: 0.5 * 1 + 0.5 * [2, 1] = [1.5, 1.0]; sum: 0.5 * e + 0.5 * (sum of assigned z).
    count = torch.tensor([1.5, 1.0])
    s0 = 0.5 * torch.tensor([1.0, 0.0]) + 0.5 * (z[0] + z[1])
    s1 = 0.5 * torch.tensor([0.0, 1.0]) + 0.5 * z[2]
    torch.testing.assert_close(vq.ema_count, count)
    torch.testing.assert_close(vq.codebook[0], F.normalize(s0 / 1.5, dim=0))
    torch.testing.assert_close(vq.codebook[1], F.normalize(s1 / 1.0, dim=0))


def test_dead_codes_are_reseeded():
    torch.manual_seed(0)
    vq = VectorQuantizerEMA(3, 2, dead_after=2)
    vq.init_codebook(torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]))
    z = F.normalize(torch.tensor([[1.0, 0.1], [0.1, 1.0]]), dim=-1)
    for _ in range(2):
        vq.ema_update(z, vq.nearest(z))
    # Codeword 2 was never used: it now sits on one of the batch latents.
    assert min((vq.codebook[2] - z[i]).norm() for i in range(2)) < 1e-6


def test_dropout_rates_and_masks():
    r = dropout_rates(8, 0.7, protected=2)
    assert r[:2].tolist() == [0.0, 0.0] and r[-1].item() == pytest.approx(0.7)
    assert torch.all(r[1:] >= r[:-1])
    mask = sample_drop_mask(20000, r, torch.Generator().manual_seed(0))
    torch.testing.assert_close(mask.float().mean(0), r, atol=0.02, rtol=0)


@pytest.mark.parametrize("err,expected", [
    ([0.5, 0.2, 0.05, 0.049, 0.048, 0.048], 3),  # clear elbow
    ([0.1, 0.1, 0.1, 0.1], 1),  # flat: one material explains everything
    ([0.3, 0.1, 0.0995, 0.101, 0.0985, 0.1005], 2),  # noisy tail within eps
    ([0.3, 0.1, 0.099, 0.101, 0.095, 0.094], 5),  # a later drop larger than eps moves the choice
    ([0.4, 0.3, 0.2, 0.1], 4),  # never flattens: all codewords
])
def test_choose_num_materials(err, expected):
    assert choose_num_materials(err, eps=0.002) == expected


def test_forced_assignments_get_no_straight_through_gradient():
    vq = VectorQuantizerEMA(2, 2, dead_after=1000)
    vq.init_codebook(torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    vq.eval()
    z = torch.tensor([[1.0, 0.1], [0.1, 1.0]], requires_grad=True)
    drop = torch.tensor([[True, False], [False, False]])  # latent 0's own codeword is dropped
    z_q, idx, loss = vq(z, drop)
    assert idx.tolist() == [1, 1]
    (z_q.sum() + loss).backward()
    assert z.grad[0].abs().max() == 0  # forced onto codeword 1: no gradient, no commitment pull
    assert z.grad[1].abs().max() > 0
    z.grad = None
    z_q, _, loss = vq(z, None)  # without dropout the straight-through gradient reaches both
    (z_q.sum() + loss).backward()
    assert z.grad[0].abs().max() > 0


def test_warm_started_discrete_decoder_matches_the_continuous_one_at_the_codewords():
    from types import SimpleNamespace

    from vq_mitsuba.models.fields import BRDFDecoder
    from vq_mitsuba.models.vq import DiscreteBranch

    torch.manual_seed(1)
    cfg = SimpleNamespace(latent=6, decoder_hidden=16, roughness_min=0.02, metallic_init=0.05)
    cont = BRDFDecoder(cfg)
    branch = DiscreteBranch(cfg, num_codes=3, decay=0.99, commitment=0.1)
    latents = 2.5 * F.normalize(torch.randn(300, 6), dim=-1)  # typical length 2.5
    branch.vq.init_codebook(latents[:3])
    branch.warm_start(cont, latents)
    assert float(branch.latent_scale) == pytest.approx(2.5, rel=1e-4)
    got = branch.codeword_brdfs()
    want = cont(latents[:3])  # these latents are the codewords, at the same length
    for k in ("basecolor", "metallic", "roughness"):
        torch.testing.assert_close(got[k], want[k], atol=1e-5, rtol=1e-5)
    branch.eval()  # a latent equal to a codeword decodes to that codeword's BRDF
    out = branch(latents[1:2])
    torch.testing.assert_close(out["basecolor"], want["basecolor"][1:2], atol=1e-5, rtol=1e-5)


def test_reorder_permutes_codewords_and_their_statistics():
    vq = VectorQuantizerEMA(3, 2, dead_after=1000)
    vq.init_codebook(torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]))
    vq.ema_count.copy_(torch.tensor([1.0, 2.0, 3.0]))
    z = torch.tensor([[0.0, 1.0]])
    assert vq.nearest(z).item() == 1
    vq.reorder(torch.tensor([1, 2, 0]))
    assert vq.ema_count.tolist() == [2.0, 3.0, 1.0]
    assert vq.nearest(z).item() == 0  # the same codeword, now first
    torch.testing.assert_close(vq.ema_sum, vq.codebook)


def test_duplicate_codewords_rank_behind_the_distinct_ones():
    from vq_mitsuba.models.vq import duplicates_last

    brdf = {
        "basecolor": torch.tensor([[0.8, 0.1, 0.1], [0.2, 0.2, 0.8], [0.79, 0.11, 0.1], [0.8, 0.1, 0.1], [0.5, 0.5, 0.5]]),
        "metallic": torch.tensor([0.0, 0.0, 0.01, 1.0, 0.0]),
        "roughness": torch.tensor([0.5, 0.5, 0.52, 0.5, 0.5]),
    }
    # 2 repeats 0's material; 3 has 0's colour but is a metal (distinct); 4 is unused.
    order, n = duplicates_last(brdf, [0, 2, 1, 3, 4], n_used=4, tol=0.1)
    assert order == [0, 1, 3, 2, 4] and n == 3
    # the first of two duplicates keeps its place, whichever index it has
    order, n = duplicates_last(brdf, [2, 0, 1, 3, 4], n_used=4, tol=0.1)
    assert order == [2, 1, 3, 0, 4] and n == 3
    # tol 0 switches merging off
    assert duplicates_last(brdf, [0, 2, 1, 3, 4], n_used=4, tol=0.0) == ([0, 2, 1, 3, 4], 4)


def test_a_codeword_that_adds_nothing_moves_behind_and_err_k_is_measured_again():
    from vq_mitsuba.models.vq import redundant_last

    # Codewords 0 and 1 both decode to material A (half the pixels), 2 to B, 3 to C, 4 is unused.
    covers = {0: "A", 1: "A", 2: "B", 3: "C", 4: None}
    share = {"A": 0.5, "B": 0.3, "C": 0.2}
    calls = []

    def measure(order):  # err_k: 0.1 per unit share of pixels whose material no codeword in the prefix covers
        calls.append(list(order))
        return [0.01 + 0.1 * sum(v for m, v in share.items() if m not in {covers[i] for i in order[:k]})
                for k in range(1, len(order) + 1)]

    assert choose_num_materials(measure([0, 1, 2, 3, 4]), 0.002) == 4  # the copy of A counts as a material
    calls.clear()
    order, errs, moved = redundant_last(measure, [0, 1, 2, 3, 4], 0.002)
    assert order == [0, 2, 3, 4, 1] and moved == [1] and len(calls) == 2
    assert errs == measure(order) and choose_num_materials(errs, 0.002) == 3
    calls.clear()
    assert redundant_last(measure, [0, 2, 3, 1, 4], 0.002)[0] == [0, 2, 3, 1, 4]  # nothing to move
    assert len(calls) == 1


def test_redundant_ranking_moves_each_codeword_at_most_once():
    from vq_mitsuba.models.vq import redundant_last

    # Codewords 1 and 3 share a material: the error falls (by 0.05) only once both are in the
    # prefix, and every codeword added otherwise raises it by 0.001. Moving 1, 2, then 3 to the
    # end gives back the starting order; without the once-only rule the moves would go round.
    def measure(order):
        return [0.1 + 0.001 * k - 0.05 * float({1, 3} <= set(order[:k])) for k in range(1, len(order) + 1)]

    order, errs, moved = redundant_last(measure, [0, 1, 2, 3], 0.002)
    assert moved == [1, 2, 3] and order == [0, 1, 2, 3]
    assert errs == measure(order) and choose_num_materials(errs, 0.002) == 4


def test_a_moved_codeword_stays_ahead_of_the_duplicates_and_unused_ones():
    from vq_mitsuba.models.vq import redundant_last

    # Codewords 0-3 are distinct (n_keep = 4); 4 duplicates 3 and 5 is unused. Codeword 1 (material
    # B) adds nothing at its early position, since B's pixels stay with 0 until 2 is in too; while
    # B is not covered, the duplicate 4 takes half of B's pixels. Moved to the end of the distinct
    # block, 1 is measured there and stays among the first n_keep, ahead of the duplicate.
    share = {0: 0.4, 1: 0.2, 2: 0.25, 3: 0.15}

    def measure(order):
        def err(prefix):
            missing = sum(v for m, v in share.items() if m not in prefix)
            b_covered = 1 in prefix and 2 in prefix
            if 1 in prefix and not b_covered:
                missing += share[1]
            if 4 in prefix and not b_covered:
                missing -= share[1] / 2
            return 0.01 + 0.1 * missing
        return [err(order[:k]) for k in range(1, len(order) + 1)]

    order, errs, moved = redundant_last(measure, [0, 1, 2, 3, 4, 5], 0.002, n_keep=4)
    assert moved == [1] and order == [0, 2, 3, 1, 4, 5]
    assert errs == measure(order) and choose_num_materials(errs, 0.002) == 4
    # Moved to the very end, B would rank behind the duplicate, outside the first n_keep (the
    # number of materials is capped there), and its pixels would get the duplicate's id.
    order = redundant_last(measure, [0, 1, 2, 3, 4, 5], 0.002)[0]
    assert order.index(4) < 4 <= order.index(1)

    # A weak codeword behind n_keep (inside the chosen prefix) goes to the very end.
    def measure2(order):
        gain = {0: 0.01, 1: 0.01, 2: 0.0005, 3: 0.02}
        return [0.1 - sum(gain.get(i, 0.0) for i in order[:k]) for k in range(1, len(order) + 1)]

    order, _, moved = redundant_last(measure2, [0, 1, 2, 3, 4, 5], 0.002, n_keep=2)
    assert moved == [2] and order == [0, 1, 3, 4, 5, 2]
