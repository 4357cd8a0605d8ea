"""Bad PandaSet sequences: hostile pickles (safe mode), malformed JSON and DataFrame fields give
a ValueError naming the file, never code execution, an allocation blow-up or a bare
KeyError/TypeError."""
import gzip
import os
import pickle
import shutil

import numpy as np
import pandas as pd
import pytest

from clsplat.data.files import SAFE_PICKLE_GLOBALS, read_pickled_dataframe
from clsplat.data.pandaset import load_pandaset, write_pandaset
from clsplat.data.synthetic import generate_sequence


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    seq = generate_sequence(height=16, width=24, num_frames=2, seed=4)
    seq.metadata["lidar_semantics"] = [np.zeros(len(f.lidar.points), np.uint8) for f in seq.frames]
    return write_pandaset(seq, tmp_path_factory.mktemp("pandaset") / "001")


@pytest.fixture
def root(pristine, tmp_path):
    return shutil.copytree(pristine, tmp_path / "001")


class Payload:
    """Unpickling this runs ``os.system`` (an attacker's file would do worse)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_safe_mode_reads_what_the_writer_wrote_like_the_trusting_reader(root):
    a = load_pandaset(root, safe_pickle=False)
    b = load_pandaset(root, safe_pickle=True)
    assert np.array_equal(a.frames[1].lidar.points, b.frames[1].lidar.points)
    assert [x.uuid for x in a.frames[1].boxes] == [x.uuid for x in b.frames[1].boxes]
    assert np.array_equal(a.metadata["lidar_semantics"][0], b.metadata["lidar_semantics"][0])


@pytest.mark.parametrize("where", ["lidar/01.pkl.gz", "annotations/cuboids/00.pkl.gz",
                                   "annotations/semseg/01.pkl.gz"])
def test_safe_mode_refuses_a_pickle_that_runs_code(root, tmp_path, where):
    marker = tmp_path / "ran"
    with gzip.open(root / where, "wb") as fh:
        pickle.dump(Payload(marker), fh)
    with pytest.raises(ValueError, match=rf"{where}.*safe mode refuses.*system"):
        load_pandaset(root, safe_pickle=True)
    assert not marker.exists()


@pytest.mark.parametrize("env", [None, "0", "1"])
def test_safe_by_default_whatever_the_environment_says(root, tmp_path, monkeypatch, env):
    marker = tmp_path / "ran"
    with gzip.open(root / "lidar/00.pkl.gz", "wb") as fh:
        pickle.dump(Payload(marker), fh)
    if env is None:
        monkeypatch.delenv("CLSPLAT_SAFE_PICKLE", raising=False)
    else:  # the old opt-in variable no longer switches anything: only an explicit argument opts out
        monkeypatch.setenv("CLSPLAT_SAFE_PICKLE", env)
    with pytest.raises(ValueError, match=r"lidar/00\.pkl\.gz.*safe mode refuses.*system"):
        load_pandaset(root)
    assert not marker.exists()


def test_the_opt_out_is_explicit_and_trusts_the_file(root, tmp_path):
    marker = tmp_path / "ran"
    with gzip.open(root / "lidar/00.pkl.gz", "wb") as fh:
        pickle.dump(Payload(marker), fh)
    with pytest.raises(ValueError):  # os.system returns an int, not a DataFrame: but it has run
        load_pandaset(root, safe_pickle=False)
    assert marker.exists()


@pytest.mark.parametrize("safe", ["yes", None, 1])
def test_safe_pickle_must_be_a_bool(root, safe):
    with pytest.raises(ValueError, match="^safe_pickle: expected True"):
        load_pandaset(root, safe_pickle=safe)


def test_a_gzip_bomb_is_refused_before_it_is_decompressed_whole(tmp_path):
    p = tmp_path / "bomb.pkl.gz"
    with gzip.open(p, "wb") as fh:  # a pickled 4 MiB byte string of zeros: a few KiB compressed
        pickle.dump(bytes(4 << 20), fh, protocol=5)
    assert p.stat().st_size < 64 << 10
    for safe in (True, False):
        with pytest.raises(ValueError, match=r"bomb\.pkl\.gz.*decompresses to more than 1048576 bytes"):
            read_pickled_dataframe(p, safe=safe, max_bytes=1 << 20)


def test_old_pandas_layout_goes_through_the_compat_unpickler_with_the_same_allow_list(tmp_path, monkeypatch):
    """A pickle the C unpickler cannot rebuild falls back to pandas' compat unpickler, which
    must refuse the same globals."""
    import clsplat.data.files as files

    def broken_load(self):
        raise AttributeError("old layout")
    monkeypatch.setattr(files._SafeUnpickler, "load", broken_load)
    df = pd.DataFrame({"x": np.arange(5.0), "s": list("abcde")})
    good = tmp_path / "good.pkl.gz"
    df.to_pickle(good, compression="gzip")
    assert read_pickled_dataframe(good).equals(df)
    marker = tmp_path / "ran"
    bad = tmp_path / "bad.pkl.gz"
    with gzip.open(bad, "wb") as fh:
        pickle.dump(Payload(marker), fh)
    with pytest.raises(ValueError, match="safe mode refuses"):
        read_pickled_dataframe(bad)
    assert not marker.exists()


def test_safe_mode_refuses_pandas_functions_that_are_not_constructors(tmp_path):
    class ReadOther:
        def __reduce__(self):
            return pd.read_pickle, ("/elsewhere.pkl",)
    p = tmp_path / "x.pkl.gz"
    with gzip.open(p, "wb") as fh:
        pickle.dump(ReadOther(), fh)
    assert ("pandas.io.pickle", "read_pickle") not in SAFE_PICKLE_GLOBALS
    with pytest.raises(ValueError, match=r"x\.pkl\.gz.*safe mode refuses.*read_pickle"):
        read_pickled_dataframe(p, safe=True)


def test_pickle_of_something_else_than_a_dataframe(tmp_path):
    p = tmp_path / "l.pkl.gz"
    with gzip.open(p, "wb") as fh:
        pickle.dump([1, 2, 3], fh)
    with pytest.raises(ValueError, match=r"l\.pkl\.gz' holds a list, not a pandas DataFrame"):
        read_pickled_dataframe(p, safe=False)


def test_corrupt_gzip(root):
    (root / "lidar/00.pkl.gz").write_bytes(b"\x1f\x8bnot really")
    with pytest.raises(ValueError, match=r"lidar/00\.pkl\.gz"):
        load_pandaset(root)


# --- malformed JSON and fields ----------------------------------------------------------------
@pytest.mark.parametrize("rel,text,what", [
    ("lidar/poses.json", "[" * 100000 + "]" * 100000, "nested too deeply"),
    ("lidar/timestamps.json", "[" + "9" * 10000 + "]", "not valid JSON"),
    ("lidar/timestamps.json", '["a", "b"]', "finite numbers"),
    ("camera/front_camera/intrinsics.json", '{"fx": "x", "fy": 1, "cx": 1, "cy": 1}', "numbers fx, fy"),
    ("camera/front_camera/intrinsics.json", '{"fx": -5, "fy": 1, "cx": 1, "cy": 1}', "fx, fy must be finite and > 0"),
    ("camera/front_camera/intrinsics.json", "[1, 2]", "numbers fx, fy"),
    ("camera/front_camera/poses.json", '[{"position": 1}]', "pose must be"),
    ("annotations/semseg/classes.json", '{"99999999999": "Car"}', "class ids in 0..65535"),
    ("annotations/semseg/classes.json", '{"x": "Car"}', "class ids must be integers"),
])
def test_malformed_json(root, rel, text, what):
    (root / rel).write_text(text)
    with pytest.raises(ValueError, match=rf"{rel}.*{what}"):
        load_pandaset(root)


def rewrite(path, fn):
    df = pd.read_pickle(path, compression="gzip")
    fn(df).to_pickle(path, compression="gzip")


@pytest.mark.parametrize("fn,what", [
    (lambda df: df.drop(columns=["x"]), r"lacks columns \['x'\]"),
    (lambda df: df.assign(x="abc"), "must be numbers"),
    (lambda df: df.assign(z=np.nan), "NaN or Inf"),
])
def test_malformed_lidar_frame(root, fn, what):
    rewrite(root / "lidar/00.pkl.gz", fn)
    with pytest.raises(ValueError, match=rf"lidar/00\.pkl\.gz.*{what}"):
        load_pandaset(root)


@pytest.mark.parametrize("fn,what", [
    (lambda df: df.assign(yaw="north"), r"row 0, column 'yaw': expected a number, got 'north'"),
    (lambda df: df.assign(yaw=[[1.0, 2.0]] * len(df)), r"row 0, column 'yaw': expected a number"),
    (lambda df: df.assign(yaw=None), r"row 0, column 'yaw': expected a number, got None"),
    (lambda df: df.assign(yaw=True), r"row 0, column 'yaw': expected a number, got True"),
    (lambda df: df.assign(**{"position.y": "x"}), r"row 0, column 'position.y': expected a number"),
    (lambda df: df.assign(**{"dimensions.x": np.inf}), r"column 'dimensions.x': expected a finite number"),
    (lambda df: df.assign(**{"dimensions.z": -1.0}), r"dimensions.* must be >= 0"),
    (lambda df: df.drop(columns=["uuid"]), "lacks columns"),
])
def test_malformed_cuboids(root, fn, what):
    rewrite(root / "annotations/cuboids/00.pkl.gz", fn)
    with pytest.raises(ValueError, match=rf"cuboids/00\.pkl\.gz.*{what}"):
        load_pandaset(root)


@pytest.mark.parametrize("safe", [True, False])
@pytest.mark.parametrize("column", ["yaw", "position.x", "position.y", "position.z",
                                    "dimensions.x", "dimensions.y", "dimensions.z"])
def test_one_cuboid_cell_that_is_not_a_number(root, column, safe):
    """One bad cell in an otherwise numeric column (the column is then of object dtype: pandas
    refuses ``df.loc[1, "yaw"] = "abc"`` on a float64 column with its own TypeError, which is
    the writer's problem, not the reader's) gives one line naming the file, the row and the column."""
    def one_bad_cell(df):
        col = df[column].astype(object)
        col.iloc[1] = "abc"
        return df.assign(**{column: col})

    rewrite(root / "annotations/cuboids/00.pkl.gz", one_bad_cell)
    with pytest.raises(ValueError) as e:
        load_pandaset(root, safe_pickle=safe)
    msg = str(e.value)
    assert "\n" not in msg and "cuboids/00.pkl.gz" in msg
    assert f"row 1, column {column!r}: expected a number, got 'abc'" in msg


@pytest.mark.parametrize("frames", [["0"], [0.5], [None], [True]])
def test_frames_of_the_wrong_type(root, frames):
    with pytest.raises(ValueError, match="^frames: expected a list of ints"):
        load_pandaset(root, frames=frames)


def test_none_path():
    with pytest.raises(ValueError, match="^seq_dir: expected"):
        load_pandaset(None)


def test_json_file_over_the_size_limit(root, monkeypatch):
    monkeypatch.setattr("clsplat.data.files.MAX_JSON_BYTES", 10)
    with pytest.raises(ValueError, match=r"poses\.json.*over the 10-byte limit"):
        load_pandaset(root)
