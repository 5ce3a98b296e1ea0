"""Strict JSON files: non-finite numbers become null, finite ones are written bit for bit."""

import json
import math
import struct

import numpy as np

from mi_lidar.core.strict_json import nan_for_null, write_json


def strict_load(text: str):
    """``json.loads`` that refuses NaN, Infinity and -Infinity, as JavaScript's JSON.parse, Go and serde_json do."""

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def bits(values) -> list[bytes]:
    return [struct.pack("<d", float(v)) for v in values]


def test_non_finite_numbers_are_written_as_null_and_finite_ones_bit_for_bit(tmp_path):
    finite = [0.1, 1 / 3, -2.5e-300, 5e-324, 1.7976931348623157e308, np.float32(0.1), np.float64(2 / 3), -0.0]
    value = {
        "nan": math.nan,
        "inf": math.inf,
        "-inf": -math.inf,
        "float32": np.float32("nan"),
        "float64": np.float64("-inf"),
        "array": np.array([1.5, np.nan, np.inf], np.float32),
        "nested": {"list": [1, (np.nan, {"deep": -np.inf, "kept": 2.5})], "grid": np.array([[np.nan, 2], [3, np.inf]])},
        "finite": finite,
        "finite_array": np.array(finite[:5]),
        "other": [3, True, None, "NaN"],
    }
    read = strict_load(write_json(tmp_path / "a.json", value).read_text())
    assert read == {
        "nan": None,
        "inf": None,
        "-inf": None,
        "float32": None,
        "float64": None,
        "array": [1.5, None, None],
        "nested": {"list": [1, [None, {"deep": None, "kept": 2.5}]], "grid": [[None, 2.0], [3.0, None]]},
        "finite": read["finite"],
        "finite_array": read["finite_array"],
        "other": [3, True, None, "NaN"],
    }
    assert bits(read["finite"]) == bits(finite) and bits(read["finite_array"]) == bits(finite[:5])
    # default= converts what JSON does not know (numpy integers, as json.dumps(default=float) did), then the same
    read = strict_load(write_json(tmp_path / "b.json", [np.int64(3), np.float32(np.inf)], default=float).read_text())
    assert read == [3.0, None]


def test_null_reads_back_as_nan():
    read = nan_for_null({"J": None, "J_runs": [0.5, None], "points": 12, "nested": {"f1": None}})
    assert math.isnan(read["J"]) and read["J_runs"][0] == 0.5 and math.isnan(read["J_runs"][1])
    assert read["points"] == 12 and math.isnan(read["nested"]["f1"])
