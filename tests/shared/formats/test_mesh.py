"""Triangle meshes from OBJ: fans, negative indices, and errors naming the line."""

from __future__ import annotations

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.mesh import parse_obj


def test_quads_become_fans_and_negative_indices_count_back() -> None:
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1/1 2/2/2 3/3/3 4/4/4\nv 0 0 1\nf -1 1 2\n"
    mesh = parse_obj(text)
    assert mesh.vertices.shape == (5, 3)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 0, 1]]
    assert np.allclose(mesh.vertices[4], [0, 0, 1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("v 0 0\nf 1 2 3\n", "m.obj:1: vertex line needs three coordinates"),
        ("v 0 0 0\nv 1 0 0\nf 1 2\n", "m.obj:3: face line needs at least three vertices"),
        ("v 0 0 0\nf a b c\n", "m.obj:2: face indices are not integers"),
        ("v 0 0 0\n", "m.obj: OBJ file holds no faces"),
    ],
)
def test_bad_obj_names_the_line(text: str, message: str) -> None:
    with pytest.raises(InputError, match=message):
        parse_obj(text, "m.obj")
