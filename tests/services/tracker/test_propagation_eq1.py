"""Eq. 1 label propagation: exact against a brute-force reading of the equation, and the
behaviours the tracker relies on (shift following, window, top-k softmax, no-track slot)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.tracker.propagation import (  # noqa: E402
    LabelPropagator,
    benchmark_propagation,
    propagate_labels,
)
from shared.config.tracker import PropagationConfig  # noqa: E402


def unit(*shape, gen):
    return torch.nn.functional.normalize(torch.randn(*shape, generator=gen), dim=-1)


def brute_force(feats, refs, radius, k, temperature):
    """Eq. 1 patch by patch, candidates over every reference, exactly as written."""
    h, w, _ = feats.shape
    n_slots = refs[0][1].shape[-1]
    out = np.zeros((h, w, n_slots))
    for y in range(h):
        for x in range(w):
            cand = []
            for rf, ry in refs:
                for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                    for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                        cand.append((float(feats[y, x] @ rf[yy, xx]), ry[yy, xx].numpy()))
            cand.sort(key=lambda c: -c[0])
            top = cand[:k]
            s = np.array([c[0] for c in top]) / temperature
            a = np.exp(s - s.max())
            a /= a.sum()
            out[y, x] = sum(ai * lab for ai, (_, lab) in zip(a, top, strict=True))
    return out


@pytest.mark.parametrize(
    ("h", "w", "radius", "k", "n_refs", "chunk"),
    [
        (11, 13, 3, 5, 3, 1 << 20),  # wider than tall: the transposed path
        (13, 11, 3, 5, 3, 1 << 20),
        (7, 20, 2, 4, 2, 2000),  # tiny chunks: several row chunks
        (5, 6, 12, 5, 2, 1 << 20),  # window larger than the grid
        (12, 12, 1, 3, 1, 1 << 20),
        (1, 7, 2, 5, 1, 1 << 20),
        (1, 1, 12, 5, 1, 1 << 20),  # fewer candidates than k
    ],
)
def test_matches_brute_force(h, w, radius, k, n_refs, chunk):
    gen = torch.Generator().manual_seed(h * 100 + w)
    feats = unit(h, w, 8, gen=gen)
    refs = [(unit(h, w, 8, gen=gen), torch.softmax(torch.randn(h, w, 4, generator=gen), -1)) for _ in range(n_refs)]
    expected = brute_force(feats, refs, radius, k, 0.2)
    # The torch path with one reference per matmul or all at once (CUDA's way), and the CPU's
    # numba kernel (services/tracker/propagation_numba.py) where numba is installed.
    for batch_refs, use_numba in ((False, False), (True, False), (None, True)):
        got = propagate_labels(
            feats, refs, window_radius=radius, topk=k, temperature=0.2, batch_refs=batch_refs, chunk_bytes=chunk, use_numba=use_numba
        )
        assert got.shape == (h, w, 4) and got.dtype == torch.float32
        np.testing.assert_allclose(got.numpy(), expected, atol=1e-5)


def test_topk_softmax_hand_case():
    """Cosines 1.0, 0.8, ..., 0.0 to six references: the best five, softmax of cos / 0.2."""
    cos = torch.tensor([1.0, 0.8, 0.6, 0.4, 0.2, 0.0])
    ref = torch.stack([cos, torch.sqrt(1 - cos**2)], -1).view(1, 6, 2)
    cur = torch.tensor([1.0, 0.0]).expand(1, 6, 2).contiguous()
    labels = torch.eye(7)[1:].view(1, 6, 7)  # reference patch j carries slot j + 1
    y = propagate_labels(cur, [(ref, labels)], window_radius=12, topk=5, temperature=0.2)
    expected = [0.0, 0.636409, 0.234122, 0.086129, 0.031685, 0.011656, 0.0]
    for x in range(6):
        np.testing.assert_allclose(y[0, x].numpy(), expected, atol=2e-6)
    z = sum(math.exp(v) for v in (5, 4, 3, 2, 1))
    assert y[0, 0, 1].item() == pytest.approx(math.exp(5) / z, abs=1e-6)


def test_temperature_and_k_change_the_weights():
    cos = torch.tensor([1.0, 0.8, 0.6])
    ref = torch.stack([cos, torch.sqrt(1 - cos**2)], -1).view(1, 3, 2)
    cur = torch.tensor([1.0, 0.0]).expand(1, 3, 2).contiguous()
    labels = torch.eye(3).view(1, 3, 3)
    y = propagate_labels(cur, [(ref, labels)], window_radius=5, topk=2, temperature=0.1)
    e = math.exp(2.0)  # (1.0 - 0.8) / 0.1
    np.testing.assert_allclose(y[0, 0].numpy(), [e / (e + 1), 1 / (e + 1), 0.0], atol=1e-6)


def test_window_radius_excludes_far_matches():
    w = 30
    e = torch.tensor([1.0, 0.0])
    half = torch.tensor([0.5, math.sqrt(0.75)])
    ref = half.expand(1, w, 2).clone()
    ref[0, 20] = e  # a perfect match, 5 patches from patch 15
    labels = torch.zeros(1, w, 3)
    labels[0, :, 1] = 1.0
    labels[0, 20] = torch.tensor([0.0, 0.0, 1.0])
    cur = e.expand(1, w, 2).contiguous()
    y = propagate_labels(cur, [(ref, labels)], window_radius=2, topk=5, temperature=0.2)
    assert y[0, 15].argmax() == 1 and y[0, 15, 2] == 0  # out of reach
    assert y[0, 18].argmax() == 2  # 2 patches away: within the window


def test_labels_follow_a_two_patch_shift():
    """The current frame is the reference moved right by 2 (or down by 2) patches."""
    gen = torch.Generator().manual_seed(5)
    for h, w, dy, dx in [(12, 16, 0, 2), (16, 12, 2, 0), (12, 16, 2, 2)]:
        ref = unit(h, w, 64, gen=gen)
        slots = torch.zeros(h, w, dtype=torch.long)
        slots[2:6, 3:8] = 1
        slots[7:11, 9:14] = 2
        slots[1:4, 11:15] = 3
        labels = torch.nn.functional.one_hot(slots, 4).float()
        cur = unit(h, w, 64, gen=gen)  # uncovered border: new content
        cur[dy:, dx:] = ref[: h - dy, : w - dx]
        y = propagate_labels(cur, [(ref, labels)])
        moved = y.argmax(-1)[dy:, dx:]
        assert torch.equal(moved, slots[: h - dy, : w - dx])
        assert torch.allclose(y.sum(-1), torch.ones(h, w), atol=1e-5)


def test_no_track_slot_is_carried():
    """Slot 0 (no track) is an ordinary channel: a uniform mix survives unchanged."""
    gen = torch.Generator().manual_seed(7)
    h, w = 6, 9
    dist = torch.tensor([0.7, 0.3, 0.0])
    refs = [(unit(h, w, 16, gen=gen), dist.expand(h, w, 3).contiguous()) for _ in range(3)]
    y = propagate_labels(unit(h, w, 16, gen=gen), refs)
    assert torch.allclose(y, dist.expand(h, w, 3), atol=1e-6)


def test_best_matches_come_from_any_reference():
    """Top-k runs over (q, r) jointly: a perfect match in the second reference wins."""
    gen = torch.Generator().manual_seed(9)
    h, w = 5, 5
    cur = unit(h, w, 32, gen=gen)
    far = (unit(h, w, 32, gen=gen), torch.nn.functional.one_hot(torch.ones(h, w, dtype=torch.long), 3).float())
    near = (cur.clone(), torch.nn.functional.one_hot(torch.full((h, w), 2), 3).float())
    y = propagate_labels(cur, [far, near], window_radius=2, topk=1)
    assert torch.equal(y.argmax(-1), torch.full((h, w), 2))


def test_bad_inputs_raise():
    f = torch.zeros(4, 4, 8)
    with pytest.raises(ValueError, match="at least one"):
        propagate_labels(f, [])
    with pytest.raises(ValueError, match="reference 0"):
        propagate_labels(f, [(torch.zeros(4, 5, 8), torch.zeros(4, 5, 2))])
    with pytest.raises(ValueError, match="reference 1"):
        propagate_labels(f, [(f, torch.zeros(4, 4, 2)), (f, torch.zeros(4, 4, 3))])


def test_propagator_keeps_keyframe_and_recent_frames():
    cfg = PropagationConfig(context_frames=2)
    prop = LabelPropagator(cfg)
    assert not prop.ready
    with pytest.raises(RuntimeError):
        prop.step(torch.zeros(3, 3, 4))
    gen = torch.Generator().manual_seed(11)
    key = unit(3, 4, 8, gen=gen)
    prop.reset(key, torch.nn.functional.one_hot(torch.zeros(3, 4, dtype=torch.long), 2).float())
    assert prop.ready and prop.num_slots == 2 and len(prop.references()) == 1
    frames = [unit(3, 4, 8, gen=gen) for _ in range(4)]
    for i, f in enumerate(frames):
        y = prop.step(f)
        assert y.shape == (3, 4, 2)
        refs = prop.references()
        assert len(refs) == 1 + min(i + 1, 2)
        assert refs[0][0] is key and refs[-1][0] is f
    prop.reset(key, torch.zeros(3, 4, 2))
    assert len(prop.references()) == 1

    solo = LabelPropagator(PropagationConfig(context_frames=0))
    solo.reset(key, torch.ones(3, 4, 1))
    solo.step(frames[0])
    assert len(solo.references()) == 1


def test_benchmark_returns_milliseconds():
    ms = benchmark_propagation(6, 8, 16, 2, 3, repeats=1)
    assert ms > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    gen = torch.Generator().manual_seed(13)
    feats = unit(20, 30, 64, gen=gen)
    refs = [(unit(20, 30, 64, gen=gen), torch.softmax(torch.randn(20, 30, 5, generator=gen), -1)) for _ in range(4)]
    cpu = propagate_labels(feats, refs)
    cuda_refs = [(f.cuda(), y.cuda()) for f, y in refs]
    exact = propagate_labels(feats.cuda(), cuda_refs, precision="float32")
    assert torch.allclose(cpu, exact.cpu(), atol=1e-4)
    # float16 similarities: near-tied k-th candidates may swap, so compare in aggregate.
    half = propagate_labels(feats.cuda(), cuda_refs).cpu()
    assert (cpu - half).abs().mean() < 0.01
    assert (cpu.argmax(-1) == half.argmax(-1)).float().mean() > 0.97
