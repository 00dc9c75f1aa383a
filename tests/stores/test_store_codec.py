"""The binary object encoding of the Redis store: exact round trips, documented precision, corrupt input."""

from __future__ import annotations

import json
import zlib

import numpy as np
import pytest

from arcloud.core.fusion import VOTE_STEP
from arcloud.core.types import AABB, N_CLASSES, OBB, MapObject
from arcloud.core.voxels import KEY_OFFSET, pack_keys
from arcloud.errors import InvalidInput, StoreError
from arcloud.stores import codec


def random_voxels(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ijk = rng.integers(-KEY_OFFSET, KEY_OFFSET, size=(n, 3))  # the whole key range, negative indices included
    keys = np.unique(pack_keys(ijk))
    weights = rng.random(keys.size, np.float32) * 100
    votes = rng.random((keys.size, N_CLASSES), np.float32) * (rng.random((keys.size, N_CLASSES)) < 0.3)
    return keys, weights, votes


HEADER_BYTES = 21  # format 5 without a grid: 12 bytes, then the plane kinds, the vote count and the prediction


def random_colors(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(n, 3), dtype=np.uint8)


@pytest.mark.parametrize("n", [0, 1, 7, 5000])
def test_voxels_round_trip_exactly(n: int) -> None:
    keys, weights, votes = random_voxels(n, seed=n)
    seen = weights + np.float32(2.5)
    colors = random_colors(keys.size, seed=n)
    blob = codec.encode_voxels(keys, weights, votes, seen=seen, colors=colors)
    got_keys, got_weights, got_votes, got_seen, got_colors = codec.decode_voxels(blob)
    np.testing.assert_array_equal(got_keys, keys)
    np.testing.assert_array_equal(got_weights, weights)
    np.testing.assert_array_equal(got_seen, seen)
    np.testing.assert_array_equal(got_votes, votes)
    assert got_colors is not None
    np.testing.assert_array_equal(got_colors, colors)
    assert (got_keys.dtype, got_weights.dtype, got_votes.dtype, got_colors.dtype) == (np.int64, np.float32, np.float32, np.uint8)
    assert got_votes.shape == (keys.size, N_CLASSES) and got_colors.shape == (keys.size, 3)
    assert got_keys.flags.writeable and got_weights.flags.writeable and got_votes.flags.writeable
    assert got_colors.flags.writeable


def test_colours_take_three_bytes_a_voxel_at_most_and_unknown_ones_none() -> None:
    keys, weights, votes = random_voxels(2000, seed=8)
    without = codec.encode_voxels(keys, weights, votes)
    with_colors = codec.encode_voxels(keys, weights, votes, colors=random_colors(keys.size, seed=8))
    assert without[5] & codec.FLAG_COLORS == 0 and with_colors[5] & codec.FLAG_COLORS
    assert len(zlib.decompress(with_colors[HEADER_BYTES:])) - len(zlib.decompress(without[HEADER_BYTES:])) == 3 * keys.size
    assert codec.decode_voxels(without)[4] is None
    # Alike neighbours (one surface in two shades) cost far less than 3 bytes a voxel.
    plain = np.where(np.arange(keys.size)[:, None] % 50 < 25, [200, 60, 40], [190, 62, 41]).astype(np.uint8)
    assert len(codec.encode_voxels(keys, weights, votes, colors=plain)) - len(without) < 0.5 * keys.size


def test_compact_objects_compress_well() -> None:
    # a dense 20^3 block of voxels with one dominant label: the usual shape of an object
    ijk = np.stack(np.meshgrid(*(np.arange(20),) * 3, indexing="ij"), axis=-1).reshape(-1, 3) + 400
    keys = np.sort(pack_keys(ijk))
    weights = np.ones(keys.size, np.float32) * 3
    votes = np.zeros((keys.size, N_CLASSES), np.float32)
    votes[:, 1] = 2.75  # votes come in steps of VOTE_STEP
    blob = codec.encode_voxels(keys, weights, votes)
    assert blob[4] == codec.FORMAT_VERSION and blob[5] & codec.FLAG_ZLIB
    raw_bytes = keys.size * (8 + 4 + 4 * N_CLASSES)
    assert len(blob) < raw_bytes / 50
    np.testing.assert_array_equal(codec.decode_voxels(blob)[0], keys)


def test_counts_and_votes_in_steps_are_stored_as_integers_and_other_values_as_float32() -> None:
    keys, _, _ = random_voxels(400, seed=3)
    rng = np.random.default_rng(3)
    counts = rng.integers(0, 700, keys.size).astype(np.float32)
    votes = np.zeros((keys.size, N_CLASSES), np.float32)
    votes[np.arange(keys.size), rng.integers(0, N_CLASSES, keys.size)] = rng.integers(1, 64 * 400, keys.size) * np.float32(
        VOTE_STEP
    )
    blob = codec.encode_voxels(keys, counts, votes, seen=counts + 70000)  # seen above 2**16: 32-bit
    assert tuple(blob[12:15]) == (codec.KIND_U16, codec.KIND_U32, codec.KIND_U16)
    assert int.from_bytes(blob[15:19], "little") == keys.size  # one vote a voxel
    _, got_counts, got_votes, got_seen, _ = codec.decode_voxels(blob)
    np.testing.assert_array_equal(got_counts, counts)
    np.testing.assert_array_equal(got_seen, counts + 70000)
    np.testing.assert_array_equal(got_votes, votes)
    # Values no integer plane holds exactly (fractions, negatives, -0.0, NaN, too large): float32, bit for bit.
    odd = counts.copy()
    odd[:5] = [0.3, -1.0, -0.0, np.nan, 2.0**40]
    odd_votes = votes * np.float32(1.001)
    blob = codec.encode_voxels(keys, odd, odd_votes)
    assert tuple(blob[12:15]) == (codec.KIND_F32, codec.KIND_F32, codec.KIND_F32)
    _, got_odd, got_odd_votes, _, _ = codec.decode_voxels(blob)
    np.testing.assert_array_equal(got_odd.view(np.uint32), odd.view(np.uint32))
    np.testing.assert_array_equal(got_odd_votes, odd_votes)
    assert len(blob) > len(codec.encode_voxels(keys, counts, votes)) + keys.size  # integers: over a byte a voxel less


def test_encode_rejects_malformed_voxels() -> None:
    keys, weights, votes = random_voxels(10, seed=1)
    with pytest.raises(InvalidInput, match="keys"):
        codec.encode_voxels(keys[::-1].copy(), weights, votes)
    with pytest.raises(InvalidInput, match="keys"):
        codec.encode_voxels(keys.astype(np.int32), weights, votes)
    with pytest.raises(InvalidInput, match="weights"):
        codec.encode_voxels(keys, weights[:-1], votes)
    with pytest.raises(InvalidInput, match="votes"):
        codec.encode_voxels(keys, weights, votes[:, 0])
    with pytest.raises(InvalidInput, match="colors"):
        codec.encode_voxels(keys, weights, votes, colors=random_colors(9, seed=1))
    with pytest.raises(InvalidInput, match="colors"):
        codec.encode_voxels(keys, weights, votes, colors=random_colors(10, seed=1).astype(np.float32))


def test_decode_refuses_corrupt_blobs() -> None:
    keys, weights, votes = random_voxels(500, seed=2)
    blob = codec.encode_voxels(keys, weights, votes)
    with pytest.raises(StoreError, match="header"):
        codec.decode_voxels(blob[:5])
    with pytest.raises(StoreError, match="magic"):
        codec.decode_voxels(b"XXXX" + blob[4:])
    with pytest.raises(StoreError, match="zlib"):
        codec.decode_voxels(blob[:HEADER_BYTES] + b"not zlib at all")
    with pytest.raises(StoreError, match="corrupt header"):
        codec.decode_voxels(blob[:12] + bytes([7]) + blob[13:])  # no such plane kind
    with pytest.raises(StoreError, match="bytes"):  # one vote fewer than the arrays hold
        codec.decode_voxels(blob[:15] + (int.from_bytes(blob[15:19], "little") - 1).to_bytes(4, "little") + blob[19:])
    raw = bytearray(codec.encode_voxels(keys[:3], weights[:3], votes[:3]))  # float32 weights and seen, stored raw
    raw[HEADER_BYTES + 3 * (8 + 4 + 4)] ^= 1  # the first voxel's vote bit of class 0
    with pytest.raises(StoreError, match="vote bits"):
        codec.decode_voxels(bytes(raw))
    small = codec.encode_voxels(keys[:3], weights[:3], votes[:3])  # stored raw
    with pytest.raises(StoreError, match="bytes"):
        codec.decode_voxels(small[:-1])
    coloured = codec.encode_voxels(keys[:3], weights[:3], votes[:3], colors=random_colors(3, seed=2))
    with pytest.raises(StoreError, match="bytes"):
        codec.decode_voxels(coloured[:-1])
    with pytest.raises(StoreError, match="version"):
        codec.decode_voxels(coloured[:4] + bytes([codec.FORMAT_VERSION + 1]) + coloured[5:])


def test_object_round_trips_through_metadata_and_voxels() -> None:
    keys, weights, votes = random_voxels(50, seed=4)
    rotation = np.array([[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]])
    obj = MapObject(
        id=17,
        keys=keys,
        weights=weights,
        votes=votes,
        n_frames=12,
        devices=frozenset({"b", "a", "ü-device"}),
        score_sum=3.141592653589793,
        version=5,
        created_at_s=1_700_000_000.000001,
        updated_at_s=1_700_000_001.5,
        label="tv",
        score=0.1 + 0.2,
        aabb=AABB(np.array([-1.1, 0.2, 0.3]), np.array([1.0, 2.0, 3.0000000001])),
        obb=OBB(center=np.array([0.1, 0.2, 0.3]), size=np.array([1.0, 2.0, 0.5]), rotation=rotation, yaw_rad=0.9272952180016122),
        bounds=AABB(np.array([-2.0, 0.0, 0.0]), np.array([2.0, 3.0, 4.0])),
        apart={3: 4, 250: 1},
        spanned={3: 2},
        wall_votes={0: (3, -10011), 271: (1, 4)},
    )
    colors = random_colors(keys.size, seed=4)
    meta_blob = codec.encode_meta(obj)
    got = codec.decode_object(17, meta_blob, codec.encode_voxels(keys, weights, votes, colors=colors))
    for name in (
        "id",
        "n_frames",
        "devices",
        "score_sum",
        "version",
        "created_at_s",
        "updated_at_s",
        "label",
        "score",
        "apart",
        "spanned",
        "wall_votes",
    ):
        assert getattr(got, name) == getattr(obj, name), name
    # an object without them stores the bytes it did
    bare = zlib.decompressobj(zdict=codec.META_DICTIONARY).decompress(
        codec.encode_meta(obj.replace(apart={}, spanned={}, wall_votes={}))
    )
    assert not any(name in bare for name in (b'"apart"', b'"spanned"', b'"wall_votes"'))
    np.testing.assert_array_equal(got.keys, keys)
    np.testing.assert_array_equal(got.colors, colors)
    assert not got.colors.flags.writeable  # a MapObject's voxel arrays are read-only
    for box in ("aabb", "bounds"):
        np.testing.assert_array_equal(getattr(got, box).min, getattr(obj, box).min)
        np.testing.assert_array_equal(getattr(got, box).max, getattr(obj, box).max)
    np.testing.assert_array_equal(got.obb.rotation, rotation)
    assert got.obb.yaw_rad == obj.obb.yaw_rad
    meta = codec.decode_meta(17, meta_blob)
    assert (meta.n_voxels, meta.n_devices, meta.version, meta.label) == (keys.size, 3, 5, "tv")
    assert codec.meta_of(obj).n_voxels == meta.n_voxels
    bounds = codec.unpack_boxes([codec.pack_box(obj.bounds), codec.pack_box(obj.aabb)])
    np.testing.assert_array_equal(bounds, [[-2, 0, 0, 2, 3, 4], [*obj.aabb.min, *obj.aabb.max]])


def dictionary_compressed(json_bytes: bytes) -> bytes:
    compressor = zlib.compressobj(zdict=codec.META_DICTIONARY)
    return compressor.compress(json_bytes) + compressor.flush()


def test_metadata_is_json_compressed_against_the_dictionary() -> None:
    keys, weights, votes = random_voxels(3, seed=7)
    obj = MapObject(id=4, keys=keys, weights=weights, votes=votes, label="chair", score=0.5, devices=frozenset({"d1"}))
    blob = codec.encode_meta(obj)
    unpacker = zlib.decompressobj(zdict=codec.META_DICTIONARY)
    plain = unpacker.decompress(blob)
    assert plain.startswith(b'{"label":"chair"') and len(blob) < len(plain)
    assert len(blob) < len(zlib.compress(plain)) - 40  # the dictionary spells the field names
    got = codec.decode_metas([4, 4], [blob, blob])
    assert [repr(m) for m in got] == [repr(codec.meta_of(obj))] * 2
    for without_dictionary in (plain, zlib.compress(plain)):  # what no writer writes
        with pytest.raises(StoreError, match="dictionary"):  # none, or none known
            codec.decode_meta(4, without_dictionary)
    unknown = zlib.compressobj(zdict=b"another dictionary")
    with pytest.raises(StoreError, match="unknown dictionary"):
        codec.decode_meta(4, unknown.compress(plain) + unknown.flush())
    bomb = dictionary_compressed(b'{"label":"' + b"x" * (codec.MAX_META_BYTES + 10) + b'"}')
    with pytest.raises(StoreError, match="more than"):
        codec.decode_meta(4, bomb)


def test_object_without_boxes_round_trips() -> None:
    keys, weights, votes = random_voxels(3, seed=5)
    obj = MapObject(id=1, keys=keys, weights=weights, votes=votes)
    got = codec.decode_object(1, codec.encode_meta(obj), codec.encode_voxels(keys, weights, votes))
    assert got.aabb is None and got.obb is None and got.bounds is None and got.devices == frozenset() and got.colors is None


def test_decode_refuses_keys_that_are_not_sorted_unique() -> None:
    """Keys stored as differences were summed as they came: a blob of shuffled or repeated keys (a snapshot's, written
    by hand) read as an object whose voxels every later step miscounted, or that failed every frame seeing it."""
    keys = pack_keys(np.array([[0, 0, 0], [0, 500, 0], [0, 0, 900], [7, 0, 0]]))  # far apart: stored as differences
    keys.sort()
    weights, votes = np.ones(4, np.float32), np.eye(4, N_CLASSES, dtype=np.float32)
    blob = codec.encode_voxels(keys, weights, votes)  # small: stored raw, the keys first

    def with_keys(stored: np.ndarray) -> bytes:
        differences = np.diff(stored, prepend=np.int64(0)).astype("<i8")
        return blob[:HEADER_BYTES] + codec._byte_planes(differences) + blob[HEADER_BYTES + 8 * 4 :]

    assert with_keys(keys) == blob  # the keys' bytes are where this test writes them
    wraps = np.array([2**63 - 3, 2**63 - 2, 2**63 - 1, -(2**63)])  # differences all > 0, their sum past int64 (review)
    for stored in (keys[::-1], keys[[0, 2, 1, 3]], keys[[0, 1, 1, 3]], keys - keys[0] - 1, wraps):
        with pytest.raises(StoreError, match="not sorted unique voxel keys"):
            codec.decode_voxels(with_keys(stored))


def test_metadata_of_numbers_past_a_float_or_of_other_json_types_is_corrupt() -> None:
    """Infinity for an integer raised OverflowError past the codec (a 500 on a snapshot's restore); a string
    for the devices read as its letters, the string "no" as confirmed."""
    keys, weights, votes = random_voxels(3, seed=6)
    good = json.loads(codec._meta_json(MapObject(id=1, keys=keys, weights=weights, votes=votes)))
    assert codec.decode_meta(1, dictionary_compressed(json.dumps(good).encode())).n_voxels == keys.size
    for change in ({"version": float("inf")}, {"n_voxels": float("-inf")}, {"devices": "abc"}, {"confirmed": "no"}):
        with pytest.raises(StoreError, match="corrupt metadata"):
            codec.decode_meta(1, dictionary_compressed(json.dumps({**good, **change}).encode()))


def test_corrupt_metadata_is_a_store_error() -> None:
    keys, weights, votes = random_voxels(3, seed=6)
    meta = codec.encode_meta(MapObject(id=1, keys=keys, weights=weights, votes=votes))
    with pytest.raises(StoreError, match="corrupt metadata"):
        codec.decode_meta(1, dictionary_compressed(b'{"version": "not a number"}'))
    with pytest.raises(StoreError, match="corrupt metadata"):
        codec.decode_meta(1, b"\x00garbage")
    with pytest.raises(StoreError, match="voxels"):  # metadata and voxels of different writes
        codec.decode_object(1, meta, codec.encode_voxels(keys[:2], weights[:2], votes[:2]))
    with pytest.raises(StoreError, match="bounds"):
        codec.unpack_boxes([b"short"])


def test_a_blob_cannot_unpack_beyond_what_its_header_announces() -> None:
    bomb = zlib.compress(bytes(50_000_000))  # 50 MB of zeros in about 50 kB
    planes = codec._PLANES.pack(codec.KIND_F32, codec.KIND_F32, codec.KIND_F32, 0, 0)
    one_voxel = codec._HEADER.pack(codec.MAGIC, codec.FORMAT_VERSION, codec.FLAG_ZLIB, N_CLASSES, 1) + planes
    with pytest.raises(StoreError, match="expected .* bytes for 1 voxels"):
        codec.decode_voxels(one_voxel + bomb)
    too_many = codec._HEADER.pack(codec.MAGIC, codec.FORMAT_VERSION, codec.FLAG_ZLIB, N_CLASSES, codec.MAX_BLOB_VOXELS + 1)
    with pytest.raises(StoreError, match="at most"):
        codec.decode_voxels(too_many + bomb)


def compact_object(seed: int, n_labels: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Voxels shaped like a fused object: a lumpy block near the key range's low corner, integer counts
    (seen >= weights), votes in steps of about 0.6 a unit of weight (some voxels voting for ``n_labels``),
    colours of a surface with noise."""
    rng = np.random.default_rng(seed)
    ijk = np.stack(np.meshgrid(np.arange(12), np.arange(9), np.arange(15), indexing="ij"), axis=-1).reshape(-1, 3)
    ijk = ijk[rng.random(len(ijk)) < 0.6] - KEY_OFFSET  # indices at the very bottom of the key range
    keys = pack_keys(ijk)
    n = keys.size
    weights = rng.integers(1, 300, n).astype(np.float32)
    seen = weights + rng.integers(0, 40, n)
    votes = np.zeros((n, N_CLASSES), np.float32)
    steps = np.round(weights * rng.normal(0.6, 0.1, n) / VOTE_STEP).clip(1)
    votes[:, 0] = steps * np.float32(VOTE_STEP)
    for label in range(1, n_labels):
        some = rng.random(n) < 0.1
        votes[some, label] = rng.integers(1, 100, np.count_nonzero(some)) * np.float32(VOTE_STEP)
    colors = (np.array([180, 120, 90]) + rng.normal(0, 6, (n, 3))).clip(0, 255).astype(np.uint8)
    return keys, weights, votes, seen, colors


def test_compact_objects_store_keys_as_grid_bits_and_counts_and_votes_from_predictions(monkeypatch: pytest.MonkeyPatch) -> None:
    keys, weights, votes, seen, colors = compact_object(seed=11, n_labels=3)
    blob = codec.encode_voxels(keys, weights, votes, seen=seen, colors=colors)
    flags = blob[5]
    for flag in (codec.FLAG_KEYS_GRID, codec.FLAG_SEEN_EXTRA, codec.FLAG_VOTES_PREDICTED, codec.FLAG_COLORS, codec.FLAG_ZLIB):
        assert flags & flag, flag
    for got, expected in zip(codec.decode_voxels(blob), (keys, weights, votes, seen, colors), strict=True):
        np.testing.assert_array_equal(got, expected)
    # The grid's bits cost fewer bytes than the keys' differences.
    monkeypatch.setattr(codec, "GRID_CELLS_PER_VOXEL", 0)
    plain_keys = codec.encode_voxels(keys, weights, votes, seen=seen, colors=colors)
    monkeypatch.undo()
    assert not plain_keys[5] & codec.FLAG_KEYS_GRID and len(plain_keys) > len(blob) + keys.size // 4
    for got, expected in zip(codec.decode_voxels(plain_keys), (keys, weights, votes, seen, colors), strict=True):
        np.testing.assert_array_equal(got, expected)
    votes_apart = votes.copy()
    votes_apart[0, 0] *= np.float32(1.001)  # no longer in steps: every vote as float32, none predicted
    unpredicted = codec.encode_voxels(keys, weights, votes_apart, seen=seen, colors=colors)
    assert not unpredicted[5] & codec.FLAG_VOTES_PREDICTED
    np.testing.assert_array_equal(codec.decode_voxels(unpredicted)[2], votes_apart)


def test_seen_below_weights_and_votes_far_from_their_prediction_round_trip_exactly() -> None:
    keys, weights, votes, seen, colors = compact_object(seed=12)
    seen[:10] = weights[:10] - 1  # seen below weights: stored as it is
    blob = codec.encode_voxels(keys, weights, votes, seen=seen)
    assert not blob[5] & codec.FLAG_SEEN_EXTRA and blob[5] & codec.FLAG_VOTES_PREDICTED
    np.testing.assert_array_equal(codec.decode_voxels(blob)[3], seen)
    # Most voxels vote 60000 steps a unit of weight; one of weight 65535 votes one step: its difference
    # (about 3.9e9, zigzag 7.9e9) fits no integer plane, so the votes go as they are.
    far_weights = np.ones(keys.size, np.float32)
    far_votes = np.zeros_like(votes)
    far_votes[:, 0] = 60000 * np.float32(VOTE_STEP)
    far_weights[0], far_votes[0, 0] = 65535, VOTE_STEP
    far = codec.encode_voxels(keys, far_weights, far_votes)
    assert not far[5] & codec.FLAG_VOTES_PREDICTED and far[14] == codec.KIND_U16
    np.testing.assert_array_equal(codec.decode_voxels(far)[2], far_votes)
    # Zero weights predict nothing; colours at both ends of the byte wrap around exactly.
    zero_weights = weights.copy()
    zero_weights[::3] = 0
    extremes = colors.copy()
    extremes[::2] = [0, 255, 0]
    got = codec.decode_voxels(codec.encode_voxels(keys, zero_weights, votes, seen=seen, colors=extremes))
    np.testing.assert_array_equal(got[1], zero_weights)
    np.testing.assert_array_equal(got[2], votes)
    np.testing.assert_array_equal(got[4], extremes)


def test_decode_refuses_corrupt_grids() -> None:
    keys, weights, votes, seen, _ = compact_object(seed=13)
    blob = codec.encode_voxels(keys, weights, votes, seen=seen)
    grid_at = codec._HEADER.size + codec._PLANES.size
    first_and_extent = codec._GRID.unpack_from(blob, grid_at)

    def with_grid(*values: int) -> bytes:
        return blob[:grid_at] + codec._GRID.pack(*values) + blob[grid_at + codec._GRID.size :]

    with pytest.raises(StoreError, match="corrupt grid"):  # more cells than a blob may unpack
        codec.decode_voxels(with_grid(*first_and_extent[:3], 1 << 10, 1 << 10, 1 << 10))
    with pytest.raises(StoreError, match="corrupt grid"):  # below the key range
        codec.decode_voxels(with_grid(-KEY_OFFSET - 1, *first_and_extent[1:]))
    with pytest.raises(StoreError, match="corrupt grid"):  # fewer cells than voxels
        codec.decode_voxels(with_grid(*first_and_extent[:3], 1, 1, 1))
    with pytest.raises(StoreError, match="expected .* bytes|grid holds"):  # another box: the bits no longer fit
        codec.decode_voxels(with_grid(*first_and_extent[:5], first_and_extent[5] + 1))
    with pytest.raises(StoreError, match="header"):
        codec.decode_voxels(blob[: grid_at + 5])
