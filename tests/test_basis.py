"""twinfocus.imaging.basis.BasisRows: the streamed basis equals the basis built at once."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.basis import BasisRows


def test_rows_in_uneven_batches_equal_one_concatenation_and_come_back_without_a_copy():
    rng = np.random.default_rng(1)
    batches = [
        (rng.normal(size=(k, 3, 4)) + 1j * rng.normal(size=(k, 3, 4))).astype(np.complex64) for k in (1, 70, 5, 200, 3)
    ]
    rows = BasisRows()
    for i, b in enumerate(batches):
        rows.append(b)
        np.testing.assert_array_equal(rows.array(), np.concatenate(batches[: i + 1]))
    a = rows.array()
    assert a.base is rows.buf and a.dtype == np.complex64


def test_mismatched_rows_and_an_empty_basis_are_named():
    rows = BasisRows()
    with pytest.raises(TwinFocusError, match="no basis rows"):
        rows.array()
    rows.append(np.zeros((2, 3, 4), np.complex64))
    with pytest.raises(TwinFocusError, match=r"\(3, 5\) do not match"):
        rows.append(np.zeros((1, 3, 5), np.complex64))
