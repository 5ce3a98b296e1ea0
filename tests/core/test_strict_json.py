"""Strict JSON files: non-finite numbers become null, finite ones are written bit for bit."""

import json
import math
import struct

import numpy as np
import pytest

from mi_lidar.core.strict_json import NON_FINITE, dumps_exact, loads_exact, nan_for_null, write_json


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


def test_embedded_json_parses_strictly_and_reads_back_exactly():
    """dumps_exact / loads_exact: the JSON inside log, density, EXR and bag headers. Every non-finite number is
    null for a strict parser and comes back as written (inf, -inf and NaN apart), wherever it sits."""
    value = {
        "sensor": {"max_range": math.inf, "min_range": 0.5, "calibration": None, "a/b~c": [1.0, -np.inf]},
        "notes": {"rows": [[1.0, np.float32("nan")]], "grid": np.array([np.inf, 2.0]), 3: np.float64(-np.inf)},
    }
    text = dumps_exact(value)
    written = strict_load(text)
    assert written["sensor"] == {"max_range": None, "min_range": 0.5, "calibration": None, "a/b~c": [1.0, None]}
    assert written[NON_FINITE] == {
        "/sensor/max_range": "inf",
        "/sensor/a~1b~0c/1": "-inf",
        "/notes/rows/0/1": "nan",
        "/notes/grid/0": "inf",
        "/notes/3": "-inf",
    }
    back = loads_exact(text)
    expected = {**value, "notes": {"rows": [[1.0, math.nan]], "grid": [math.inf, 2.0], "3": -math.inf}}
    assert json.dumps(back) == json.dumps(expected)  # Python's json writes NaN, so NaN compares too
    assert dumps_exact({"finite": 1.5}) == '{"finite": 1.5}'  # nothing listed when there is nothing to list
    assert loads_exact('{"max_range": Infinity, "x": NaN}')["max_range"] == math.inf  # files written before


@pytest.mark.parametrize(
    "text, message",
    [
        ('{"a": 1, "$non_finite": {"/a": "inf"}}', "'/a' does not point to a null of the object"),
        ('{"a": [null], "$non_finite": {"/a/1": "inf"}}', "'/a/1' does not point to a null"),
        ('{"a": null, "$non_finite": {"/a": "Infinity"}}', "'/a': 'Infinity' is not a JSON pointer to 'inf'"),
        ('{"a": null, "$non_finite": {"a": "inf"}}', "'a': 'inf' is not a JSON pointer"),
        ('{"$non_finite": ["/a"]}', r"\$non_finite holds a list; expected an object of JSON pointers"),
    ],
)
def test_a_damaged_list_of_non_finite_numbers_is_refused(text, message):
    with pytest.raises(ValueError, match=message):
        loads_exact(text)


def test_an_object_with_the_reserved_key_or_no_object_is_refused():
    with pytest.raises(ValueError, match=r"the key '\$non_finite' is reserved"):
        dumps_exact({NON_FINITE: {}})
    with pytest.raises(TypeError, match="dumps_exact writes an object"):
        dumps_exact([math.inf])
