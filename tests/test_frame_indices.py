"""Session frame indices of the stack positions, from an ingest ``meta.json``."""

from __future__ import annotations

import numpy as np
import pytest

from surfphase.io import stack_frame_indices


def test_the_listed_indices_cut_to_the_stacks():
    out = stack_frame_indices({"frame_indices": [3, 5, 7, 9]}, 3, "m/meta.json")
    assert out.dtype == np.int64
    np.testing.assert_array_equal(out, [3, 5, 7])


def test_without_the_key_the_positions_themselves():
    for meta in ({}, {"frame_indices": None}, {"frames": "0:10:2"}):
        out = stack_frame_indices(meta, 4, "m/meta.json")
        assert out.dtype == np.int64
        np.testing.assert_array_equal(out, np.arange(4))


def test_the_frames_spec_is_not_read_as_indices():
    meta = {"frames": "2:8:2", "frame_indices": [2, 4, 6]}
    np.testing.assert_array_equal(stack_frame_indices(meta, 3, "m/meta.json"), [2, 4, 6])


@pytest.mark.parametrize("bad", ["0:3", [0, 1.5, 2], [0, True, 2], {"0": 0}, 7])
def test_malformed_names_the_file(bad):
    with pytest.raises(ValueError, match=r"^m/meta.json: frame_indices must be a list of integers"):
        stack_frame_indices({"frame_indices": bad}, 3, "m/meta.json")


def test_too_few_names_the_file_and_the_counts():
    with pytest.raises(ValueError, match=r"^m/meta.json: frame_indices lists 2 frames, .* 3$"):
        stack_frame_indices({"frame_indices": [0, 1]}, 3, "m/meta.json")


def test_empty_stacks():
    assert stack_frame_indices({"frame_indices": []}, 0, "m/meta.json").shape == (0,)
