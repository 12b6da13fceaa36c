"""InputError crosses process boundaries intact (process pools pickle worker exceptions)."""

from __future__ import annotations

import pickle
from concurrent.futures import ProcessPoolExecutor

import pytest

from shared.core.errors import InputError


def _fail(where: str) -> None:
    raise InputError(where, "truncated PNG")


def test_input_error_pickles_with_its_fields() -> None:
    err = pickle.loads(pickle.dumps(InputError("cap/col_03.png", "truncated PNG")))
    assert isinstance(err, InputError)
    assert (err.where, err.problem, str(err)) == ("cap/col_03.png", "truncated PNG", "cap/col_03.png: truncated PNG")


def test_input_error_raised_in_a_worker_process_reaches_the_caller() -> None:
    with ProcessPoolExecutor(max_workers=1) as pool, pytest.raises(InputError) as info:
        pool.submit(_fail, "cap/white.png").result()
    assert info.value.where == "cap/white.png" and info.value.problem == "truncated PNG"
