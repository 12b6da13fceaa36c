"""Labels: the API document's pattern and check_label accept exactly the same characters."""

from __future__ import annotations

import re

import pytest

from shared.core.errors import InputError
from shared.publish.labels import LABEL_PATTERN, check_label


def _accepted(c: str) -> bool:
    try:
        check_label("params.title", c)
    except InputError:
        return False
    return True


def test_document_pattern_and_check_agree_on_every_character() -> None:
    # Python's re reads the document's \uXXXX ranges as ECMA-262 does for these code points; its
    # "$" also matches before a final newline, which ECMA-262's does not: fullmatch is ECMA's reading.
    pattern = re.compile(LABEL_PATTERN)
    disagree = [hex(o) for o in range(0x110000)
                if not 0xD800 <= o <= 0xDFFF and bool(pattern.fullmatch(chr(o))) != _accepted(chr(o))]
    assert disagree == []
    # A lone surrogate (a "\ud800" escape in JSON) is refused by the check all the same.
    assert not _accepted("\ud800")


@pytest.mark.parametrize("text", [
    "کتاب\u200cخانه",          # Persian: the zero-width non-joiner is part of the word
    "क्\u200dष",                 # Devanagari: the zero-width joiner selects the half form
    "\ue8bf lettre MUFI",       # private use: the Medieval Unicode Font Initiative's letters
    "Inv. 1923/45 <b>\"a\"</b>",
])
def test_text_of_every_script_is_kept(text: str) -> None:
    assert check_label("params.title", text) == text


@pytest.mark.parametrize("char", ["\x07", "\x85", "\u202e", "\u2066"])
def test_controls_and_bidirectional_overrides_are_refused(char: str) -> None:
    with pytest.raises(InputError, match=rf"^params.title: control character U\+{ord(char):04X} is not allowed$"):
        check_label("params.title", "Vase " + char + "gsa")
