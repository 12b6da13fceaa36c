"""Bounded JSON parsing of client documents (shared.core.jsonsafe)."""

from __future__ import annotations

import json
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from shared.core.errors import InputError
from shared.core.jsonsafe import json_depth, loads_bounded, read_json_bounded


def test_parses_ordinary_documents_like_json() -> None:
    doc = {"format": "graycode-v1", "columns": [{"bit": 9, "p": "a[{.png"}], "x": -1.5e-3, "t": True, "n": None}
    assert loads_bounded(json.dumps(doc), "capture.json") == doc


@pytest.mark.parametrize("depth", [10_000, 100_000])
def test_deep_nesting_is_an_input_error_naming_the_document(depth: int) -> None:
    with pytest.raises(InputError, match=r"^params: JSON nested \d+ levels deep"):
        loads_bounded("[" * depth + "]" * depth, "params")


def test_brackets_inside_strings_do_not_count() -> None:
    text = json.dumps({"a": "[" * 5000 + '\\"' + "{" * 5000})
    assert json_depth(text.encode()) == 1
    assert loads_bounded(text, "f.json")["a"].startswith("[[[")


@pytest.mark.parametrize("literal", ["1" * 5000, "-" + "9" * 400, "1." + "0" * 100, "1e" + "9" * 50])
def test_overlong_numbers_are_refused_by_name(literal: str) -> None:
    with pytest.raises(InputError, match=r"^rig\.json: a number of \d+ characters"):
        loads_bounded('{"fx": ' + literal + "}", "rig.json")


@pytest.mark.parametrize("literal", ["1e400", "-1e309", "1.5E+999"])
def test_numbers_beyond_floats_range_are_refused_by_name(literal: str) -> None:
    # short, valid JSON, but infinite once parsed: validators downstream met int(inf)
    with pytest.raises(InputError, match=rf"^capture\.json: {re.escape(literal)} is beyond the range of a 64-bit float$"):
        loads_bounded('{"size": [' + literal + ", 48]}", "capture.json")
    assert loads_bounded('{"a": 1e308, "b": 1e-400}', "x.json") == {"a": 1e308, "b": 0.0}


@pytest.mark.parametrize("constant", ["NaN", "Infinity", "-Infinity"])
def test_non_json_constants_are_refused(constant: str) -> None:
    with pytest.raises(InputError, match=f"{constant} is not a JSON number"):
        loads_bounded(f'{{"a": {constant}}}', "scanset.json")


def test_size_is_checked_before_parsing_and_file_reads_are_bounded(tmp_path) -> None:
    with pytest.raises(InputError, match="too large"):
        loads_bounded(b"[" + b"0," * 1000 + b"0]", "body", max_bytes=100)
    big = tmp_path / "big.json"
    big.write_bytes(b'"' + b"x" * 5_000_000 + b'"')
    # The file's size (fstat) is refused before any of it is read.
    with pytest.raises(InputError, match=r"^scanset\.json: file of 5000002 bytes is too large \(at most 1024\)$"):
        read_json_bounded(big, "scanset.json", missing="missing", max_bytes=1024)


def test_malformed_and_non_utf8_name_the_document(tmp_path) -> None:
    with pytest.raises(InputError, match=r"^capture\.json: malformed JSON at line 1"):
        loads_bounded("{", "capture.json")
    with pytest.raises(InputError, match=r"^capture\.json: not UTF-8"):
        loads_bounded(b'{"a": "\xff"}', "capture.json")
    with pytest.raises(InputError, match=r"^rig\.json: no rig here$"):
        read_json_bounded(tmp_path / "absent.json", "rig.json", missing="no rig here")


def _depth(v) -> int:
    if isinstance(v, dict):
        return 1 + max((_depth(x) for x in v.values()), default=0)
    if isinstance(v, list):
        return 1 + max((_depth(x) for x in v), default=0)
    return 0


_nasty = st.text(alphabet='[]{}"\\ab', max_size=12)
_json = st.recursive(st.none() | st.integers() | _nasty,
                     lambda kids: st.lists(kids, max_size=3) | st.dictionaries(_nasty, kids, max_size=3), max_leaves=20)


@given(_json)
def test_depth_is_the_documents_own_whatever_its_strings_hold(doc) -> None:
    assert json_depth(json.dumps(doc).encode()) == _depth(doc)


def test_escaped_quotes_are_scanned_in_one_pass() -> None:
    """A string of escaped quotes with no closing quote (what a regular expression for string
    literals backtracks over quadratically: 80 kB of it took 18 s) is scanned in one linear pass;
    2 MB here would take hours if that came back."""
    text = b'["' + b'\\"' * 1_000_000 + b"]"
    assert json_depth(text) == 1
    with pytest.raises(InputError, match="malformed JSON"):
        loads_bounded(text, "body", max_bytes=4 << 20)
