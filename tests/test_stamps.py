"""The one key scheme of every cache (`ragsplat.outputs`: `Stamp`, `changed`, `digest`): a product is kept
only while its key compares equal as JSON reads it back, and a stale one names what changed."""

import math
from pathlib import Path

import numpy as np

from ragsplat.outputs import Stamp, changed, digest, jsonable


def test_a_key_compares_as_json_reads_it_back():
    key = {"size": (2, 3), "path": Path("a/b"), "gsd": np.float64(0.05), "limit": math.inf}
    assert jsonable(key) == {"size": [2, 3], "path": "a/b", "gsd": 0.05, "limit": None}
    assert type(jsonable(key)["gsd"]) is float
    assert changed(jsonable(key), key) == []


def test_a_stale_key_names_the_inputs_that_changed():
    old = {"seed": 0, "preset": "small", "steps": 100}
    assert changed(old, {"seed": 1, "preset": "small", "steps": 200}) == ["seed", "steps"]
    assert changed(old, {"seed": 0, "preset": "small"}) == ["steps"]  # an input gone counts
    assert changed(None, old) == ["key"]  # none recorded
    assert changed("abc", "abd") == ["key"]  # digests: changed or not
    assert changed("abc", "abc") == []


def test_a_stamp_holds_what_it_was_written_with(tmp_path):
    stamp = Stamp(tmp_path / "run" / "key.json")
    assert stamp.read() is None and not stamp.holds({"seed": 0})
    stamp.write({"seed": 0, "box": (1.0, 2.0)})
    assert stamp.holds({"seed": 0, "box": (1.0, 2.0)}) and stamp.holds({"seed": 0, "box": [1.0, 2.0]})
    assert not stamp.holds({"seed": 1, "box": (1.0, 2.0)})
    stamp.path.write_text("{half a fi")  # unreadable: made again
    assert stamp.read() is None and not stamp.holds({"seed": 0, "box": (1.0, 2.0)})
    stamp.write(digest("a", 1))
    assert stamp.holds(digest("a", 1)) and not stamp.holds(digest("a", 2))


def test_a_digest_is_of_the_parts_in_order():
    assert digest({"b": 1, "a": 2}) == digest({"a": 2, "b": 1})  # a dict's order is not an input
    assert digest("a", "b") != digest("b", "a")
    assert digest(Path("x")) == digest("x") and len(digest()) == 16
