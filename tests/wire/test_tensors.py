"""The wire tensor codec (``fmgs_wire.tensors``): round trips in every dtype and byte order, malformed
tensors named by field, and chunk joining."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import TensorError, from_tensor, join, row_chunks, to_tensor

DTYPES = ["float32", "float16", "float64", "int32", "int64", "uint8"]


@st.composite
def arrays(draw):
    dt = np.dtype(draw(st.sampled_from(DTYPES)))
    if draw(st.booleans()) and dt.itemsize > 1:
        dt = dt.newbyteorder(">")  # big-endian input must be encoded little-endian on the wire
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5))
    return draw(hnp.arrays(dt, shape, elements={"allow_nan": False} if dt.kind == "f" else None))


@given(arrays())
def test_tensor_round_trip(a):
    t = to_tensor(a)
    assert list(t.shape) == list(a.shape)
    b = from_tensor(t)
    assert b.shape == a.shape and b.dtype == a.dtype.newbyteorder("=") and b.dtype.isnative
    np.testing.assert_array_equal(b, a)
    # Wire bytes are little-endian whatever the input's byte order.
    assert t.data == np.ascontiguousarray(a, a.dtype.newbyteorder("<")).tobytes()
    # A non-contiguous view encodes its values, not its memory.
    if a.ndim >= 1 and a.shape[0] > 1:
        np.testing.assert_array_equal(from_tensor(to_tensor(a[::2])), a[::2])


@pytest.mark.parametrize(
    "tensor, match",
    [
        (pb.Tensor(dtype=pb.DTYPE_FLOAT32, shape=[3], data=b"\0" * 8), "needs 12 bytes, got 8"),
        (pb.Tensor(dtype=pb.DTYPE_INT64, shape=[2, 0], data=b"\0"), "needs 0 bytes"),
        (pb.Tensor(dtype=pb.DTYPE_UNSPECIFIED, shape=[1], data=b"\0" * 4), "dtype"),
        (pb.Tensor(dtype=99, shape=[1], data=b"\0" * 4), "dtype"),
        (pb.Tensor(dtype=pb.DTYPE_UINT8, shape=[-1], data=b""), "bad shape"),
        (pb.Tensor(dtype=pb.DTYPE_UINT8, shape=[1] * 9, data=b"\0"), "bad shape"),
    ],
)
def test_malformed_tensor_names_the_field(tensor, match):
    with pytest.raises(TensorError, match=match) as e:
        from_tensor(tensor, "answer.relevancy")
    assert e.value.field == "answer.relevancy" and str(e.value).startswith("answer.relevancy:")


def test_unsupported_dtype_is_refused():
    with pytest.raises(TensorError, match="unsupported dtype"):
        to_tensor(np.zeros(3, np.uint16))


def test_row_chunks_cover_the_rows_within_the_byte_budget():
    assert row_chunks(10, 8, 24) == [(0, 3), (3, 6), (6, 9), (9, 10)]
    assert row_chunks(0, 8, 24) == [(0, 0)]  # an empty answer is still one (empty) chunk
    assert row_chunks(3, 100, 10) == [(0, 1), (1, 2), (2, 3)]  # at least one row per chunk
    assert row_chunks(5, 0, 1) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]


def test_join_concatenates_along_rows():
    a, b = np.arange(6, dtype=np.int64).reshape(3, 2), np.arange(6, 10, dtype=np.int64).reshape(2, 2)
    np.testing.assert_array_equal(join([a, b]), np.arange(10).reshape(5, 2))
    assert join([a]) is a
    empty = join([], (0, 3), np.int32)
    assert empty.shape == (0, 3) and empty.dtype == np.int32


def test_token_files_share_one_format(tmp_path):
    from fmgs_wire.tokens import read_token_file

    f = tmp_path / "tokens"
    f.write_text("# read tokens\n\n  s3cret  \n# old: x\nother\n")
    assert read_token_file(f) == ["s3cret", "other"]
    f.write_text("# nothing\n\n")
    with pytest.raises(ValueError, match="no tokens"):
        read_token_file(f)
