"""stagectl.outputs: the one output-directory check and the one plain-data converter."""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from pathlib import Path

import numpy as np
import pytest

from stagectl.errors import ConfigError
from stagectl.outputs import plain, prepare_out_dir


class Colour(enum.Enum):
    RED = "red"


@dataclasses.dataclass(frozen=True)
class Inner:
    x: float
    c: Colour


def test_plain_converts_nested_structures_and_numpy():
    data = {"a": (1, np.float64(2.5), np.int32(3)), "d": Inner(math.nan, Colour.RED), 4: Path("/tmp/x"),
            "arr": np.array([[1.0, 2.0]])}
    out = plain(data)
    assert out == {"a": [1, 2.5, 3], "d": {"x": out["d"]["x"], "c": "red"}, "4": "/tmp/x", "arr": [[1.0, 2.0]]}
    assert math.isnan(out["d"]["x"])
    assert type(out["a"][1]) is float and type(out["a"][2]) is int


def test_plain_json_maps_non_finite_to_none_and_serialises():
    out = plain({"nan": math.nan, "inf": np.float64(np.inf), "ok": 1.0, "flag": True}, json=True)
    assert out == {"nan": None, "inf": None, "ok": 1.0, "flag": True}
    json.dumps(out, allow_nan=False)


def test_prepare_out_dir_creates_and_rejects(tmp_path):
    d = prepare_out_dir(tmp_path / "a" / "b")
    assert d.is_dir() and not any(d.iterdir())
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ConfigError, match=r"--dir: .*exists and is not a directory"):
        prepare_out_dir(f, "--dir")
    with pytest.raises(ConfigError, match=r"--out: cannot write to directory"):
        prepare_out_dir(f / "sub")
