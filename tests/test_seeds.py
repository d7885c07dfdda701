"""One root seed, independent streams per frame and purpose; selection ties go to the least
friction label."""

import numpy as np
import pytest
import torch

from drake_cert.certification.classifier import SmoothedClassifier, select_label
from drake_cert.certification.seeds import (
    PURPOSES,
    frame_choice_seed,
    stream_seed,
    stream_sequence,
    streams,
)
from drake_cert.errors import CertificationError


@pytest.mark.parametrize("root", [0, 12345])
def test_no_two_streams_share_a_seed_over_a_thousand_frames(root):
    test = [s for i in range(1000) for s in streams(root, i).values()]
    cal = [s for i in range(1000) for s in streams(root, i, split="calibration").values()]
    everything = test + cal + [frame_choice_seed(root)]
    assert len(test) == 1000 * len(PURPOSES)
    assert len(set(everything)) == len(everything)
    assert not set(test) & set(cal)  # calibration streams never equal test streams


def test_streams_do_not_share_draws():
    # Distinct seeds could still give overlapping generator output if they were offsets of
    # one another in a shared sequence; SeedSequence hashes them. The first 64 normals of
    # every purpose of a few frames share no value between any two streams.
    draws = []
    for i in range(20):
        for s in streams(0, i).values():
            draws.append(torch.randn(64, generator=torch.Generator().manual_seed(s)).numpy())
    draws = np.array(draws)
    same = (draws[:, None, :] == draws[None, :, :]).any(axis=2)
    np.fill_diagonal(same, False)
    assert not same.any()


def test_streams_are_the_spawned_children_of_the_root():
    root = np.random.SeedSequence(7)
    child = root.spawn(2)[1].spawn(4)[3].spawn(len(PURPOSES))[PURPOSES.index("attack")]
    assert (stream_sequence(7, "calibration", 3, "attack").generate_state(4)
            == child.generate_state(4)).all()
    assert streams(7, 3, split="calibration")["attack"] == stream_seed(7, 3, "attack",
                                                                        split="calibration")


def test_bad_seed_split_and_purpose_are_rejected():
    with pytest.raises(CertificationError, match="root seed"):
        streams(-1, 0)
    with pytest.raises(CertificationError, match="split"):
        streams(0, 0, split="train")
    with pytest.raises(CertificationError, match="purpose"):
        stream_seed(0, 0, "guess")


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
