"""One seed scheme for the whole project: named streams of a root seed, addressed by spawn keys;
selection ties go to the least friction label."""

import numpy as np
import pytest
import torch

from drake_cert.certification.classifier import SmoothedClassifier, select_label
from drake_cert.certification.seeds import (
    FRAME_PURPOSES,
    Purpose,
    child_rng,
    child_seed,
    child_sequence,
    float_key,
    frame_choice_seed,
    stream_seed,
    stream_sequence,
    streams,
    torch_generator,
)
from drake_cert.errors import CertificationError
from drake_cert.rng import MT_WORDS, mt19937_words


@pytest.mark.parametrize("root", [0, 12345])
def test_no_two_streams_share_a_seed_over_many_keys(root):
    """Every purpose over 1000 keys, both experiment splits, and the reproduction's keys."""
    test = [s for i in range(1000) for s in streams(root, i).values()]
    cal = [s for i in range(1000) for s in streams(root, i, split="calibration").values()]
    diagram = [child_seed(root, p, k) for p in Purpose for k in range(1000)]
    reproduction = [child_seed(root, Purpose.CELL, preset, owner, attack, float_key(sigma),
                               float_key(eps))
                    for preset in range(3) for owner in range(4) for attack in range(3)
                    for sigma in (0.0, 0.25, 0.5, 1.0) for eps in (0.0, 0.25, 0.5, 1.0, 2.0)]
    everything = test + cal + diagram + reproduction + [frame_choice_seed(root)]
    assert len(test) == 1000 * len(FRAME_PURPOSES)
    assert len(set(everything)) == len(everything)
    assert not set(test) & set(cal)  # calibration streams never equal test streams


def test_distinct_purposes_never_share_a_stream():
    # Distinct seeds could still give overlapping generator output if they were offsets of
    # one another in a shared sequence; SeedSequence hashes them. The first 64 normals of
    # every purpose at a few keys share no value between any two streams.
    draws = np.array([torch.randn(64, generator=torch_generator(child_seed(0, p, k))).numpy()
                      for p in Purpose for k in range(5)])
    same = (draws[:, None, :] == draws[None, :, :]).any(axis=2)
    np.fill_diagonal(same, False)
    assert not same.any()
    # A purpose is a name: its string and its member are the same stream.
    assert child_seed(3, "camera", 7) == child_seed(3, Purpose.CAMERA, 7)


def test_seeds_that_share_their_low_32_bits_draw_different_noise():
    """torch's manual_seed keeps 32 bits of a seed on CPU: with root 1 the attack stream of
    tick 14383 and the estimation stream of tick 37288 drew the same noise. Not any more."""
    attack = child_seed(1, Purpose.ATTACK, 14383)
    estimation = child_seed(1, Purpose.ESTIMATION, 37288)
    assert attack != estimation and attack % 2**32 == estimation % 2**32  # the old collision
    assert torch.equal(torch.randn(64, generator=torch.Generator().manual_seed(attack)),
                       torch.randn(64, generator=torch.Generator().manual_seed(estimation)))
    for a, b in ((attack, estimation), (5, 5 ^ 2**40), (2**62 + 9, 9)):
        first = torch.randn(64, generator=torch_generator(a))
        second = torch.randn(64, generator=torch_generator(b))
        assert not torch.isin(first, second).any()


def test_a_seed_always_draws_the_same_noise_from_the_state_it_installed():
    """Same seed, same draws (normals, uniforms, permutations); the installed state is
    mt19937_words(seed), and the first raw draws are mt19937's outputs from that state."""
    for seed in (0, 7, 2**40 + 3, 2**63 - 1, 2**64 - 1):
        a, b = torch_generator(seed), torch_generator(seed)
        assert a.initial_seed() == seed
        assert torch.equal(torch.randn(1000, generator=a), torch.randn(1000, generator=b))
        assert torch.equal(torch.rand(7, dtype=torch.float64, generator=a),
                           torch.rand(7, dtype=torch.float64, generator=b))
        assert torch.equal(torch.randperm(50, generator=a), torch.randperm(50, generator=b))
        state = torch_generator(seed).get_state().numpy().tobytes()
        assert np.array_equal(np.frombuffer(state, "<u8", MT_WORDS, 24), mt19937_words(seed))
        # int32 random_() draws mt19937's tempered output masked to 31 bits; numpy's MT19937
        # started from the same words (pos 624: twist first) gives the reference outputs.
        reference = np.random.MT19937()
        reference.state = {"bit_generator": "MT19937",
                           "state": {"key": mt19937_words(seed), "pos": MT_WORDS}}
        raw = torch.empty(700, dtype=torch.int32).random_(generator=torch_generator(seed))
        assert (raw.numpy() == (reference.random_raw(700) & 0x7FFFFFFF)).all()  # past a twist
    assert not torch.equal(torch.randn(64, generator=torch_generator(1)),
                           torch.randn(64, generator=torch_generator(2)))
    with pytest.raises(CertificationError, match="seed"):
        torch_generator(-1)
    with pytest.raises(CertificationError, match="seed"):
        torch_generator(2**64)


def test_an_unexpected_generator_state_layout_is_refused(monkeypatch):
    """On a torch whose CPU state is laid out otherwise, torch_generator raises rather than
    installing words where they do not belong (or falling back to 32-bit seeds)."""
    from drake_cert import rng

    rng._cpu_state_template.cache_clear()
    monkeypatch.setattr(rng, "_CPU_WORDS_AT", 16)  # words where `next` is
    try:
        with pytest.raises(CertificationError, match="layout"):
            torch_generator(3)
    finally:
        monkeypatch.undo()
        rng._cpu_state_template.cache_clear()
    assert torch_generator(3).initial_seed() == 3


def _distinct_streams(keys: int) -> list[int]:
    """Streams attack and estimation of root 1 at ticks 0..keys/2 - 1 (``keys`` streams): no
    two share a 63-bit seed, nor the first four words of their generator state (the low 32
    bits of the seeds, which manual_seed kept, collide about keys^2 / 2^33 times)."""
    seeds = [child_seed(1, purpose, tick) for purpose in (Purpose.ATTACK, Purpose.ESTIMATION)
             for tick in range(keys // 2)]
    words = np.array([np.random.SeedSequence(s).generate_state(4) for s in seeds])
    assert np.array_equal(words[:3], np.array([mt19937_words(s)[:4] for s in seeds[:3]]))
    assert len(set(seeds)) == keys
    assert len(np.unique(words, axis=0)) == keys
    return seeds


def test_100_000_streams_have_distinct_generator_states():
    seeds = _distinct_streams(100_000)
    assert len({s % 2**32 for s in seeds}) < 100_000  # 32-bit seeds would have collided


@pytest.mark.slow
def test_1_000_000_streams_have_distinct_generator_states():
    _distinct_streams(1_000_000)


def test_a_stream_is_the_spawned_child_of_its_root():
    """Stream (purpose, k) is what SeedSequence(root).spawn hands out at those positions, so
    frame k's streams do not depend on how many frames were drawn before it."""
    code = list(Purpose).index(Purpose.ATTACK) + 1
    child = np.random.SeedSequence(7).spawn(code + 1)[code].spawn(4)[3]
    assert (child_sequence(7, Purpose.ATTACK, 3).generate_state(4)
            == child.generate_state(4)).all()
    late = child_seed(7, Purpose.ATTACK, 17)
    for k in range(17):
        child_rng(7, Purpose.ATTACK, k).normal(size=100)  # drawing others changes nothing
    assert child_seed(7, Purpose.ATTACK, 17) == late
    # The experiments' per-frame names are streams of the same scheme.
    assert (stream_sequence(7, "calibration", 3, "attack").generate_state(4)
            == child_sequence(7, "attack", 1, 3).generate_state(4)).all()
    assert streams(7, 3, split="calibration")["attack"] == stream_seed(7, 3, "attack",
                                                                        split="calibration")


def test_float_keys_are_exact_and_machine_independent():
    assert float_key(0.25) == 0x3FD0000000000000  # IEEE-754 bits of 0.25
    assert float_key(0.1 + 0.2) != float_key(0.3)  # every distinct value is its own key
    assert float_key(-0.0) == float_key(0.0) == 0
    with pytest.raises(CertificationError, match="key"):
        float_key(-1.0)


def test_bad_seed_split_purpose_and_key_are_rejected():
    with pytest.raises(CertificationError, match="root seed"):
        streams(-1, 0)
    with pytest.raises(CertificationError, match="split"):
        streams(0, 0, split="train")
    with pytest.raises(CertificationError, match="purpose"):
        stream_seed(0, 0, "guess")
    with pytest.raises(CertificationError, match="purpose"):
        child_seed(0, "guess", 1)
    with pytest.raises(CertificationError, match="key"):
        child_seed(0, Purpose.CAMERA, -1)
    with pytest.raises(CertificationError, match="key"):
        child_seed(0, Purpose.CAMERA, True)


def test_selection_ties_go_to_the_least_friction_label():
    assert select_label(np.array([5, 3, 5])) == 2
    assert select_label(np.array([4, 4, 1])) == 1
    assert select_label(np.array([7, 0, 1])) == 0


class HalfAndHalf(torch.nn.Module):
    """Votes label 0 (grippiest) on the first half of each batch and label 2 on the second."""

    def forward(self, x):
        b = x.shape[0]
        label = (torch.arange(b) >= b // 2).long() * 2
        return torch.nn.functional.one_hot(label, 3).float()


def test_certify_resolves_a_selection_tie_to_the_conservative_label():
    smooth = SmoothedClassifier(HalfAndHalf(), 3, 0.25)
    cert = smooth.certify(torch.full((1, 4, 4), 0.5), 100, 1000, 0.001, 100, seed=0,
                          selection_seed=1)
    assert cert.top_label == 2  # 50 votes each for labels 0 and 2


def test_a_drive_draws_tick_k_and_segment_i_the_same_whatever_came_before():
    """The Diagram's streams are keyed by tick and segment: a camera that rendered ticks 0-4
    renders tick 5 as one that did not, and a longer route keeps its first segments' truth."""
    from drake_cert.config import load_conditions
    from drake_cert.systems.camera import CameraSource
    from drake_cert.systems.route import Route, SegmentSpec

    conditions = load_conditions()
    specs = [SegmentSpec(length_m=60.0, curvature_per_m=0.0, condition=c)
             for c in ("sunny", "rain", "snow")]
    short = Route.build(specs[:2], conditions, "robotcar-like", seed=5)
    long = Route.build(specs, conditions, "robotcar-like", seed=5)
    assert [s.stiffness_n_per_rad for s in long.segments[:2]] == \
           [s.stiffness_n_per_rad for s in short.segments]
    busy, fresh = (CameraSource(long, conditions, "robotcar-like", seed=9) for _ in range(2))
    for k in range(5):
        busy.capture(0.1 * k, 2.0 * k, k)
    assert torch.equal(busy.capture(0.5, 10.0, 5).image, fresh.capture(0.5, 10.0, 5).image)
    assert not torch.equal(fresh.capture(0.5, 10.0, 5).image, fresh.capture(0.5, 10.0, 6).image)
