"""docs/protocol.md's table of engine mappings, checked as written: for each engine, its position
conversion and its quaternion conversion must agree, i.e. a rotation converted by the quaternion
column, applied to a vector converted by the position column, gives the converted rotated vector
(unit scale aside). A typo in a sign of the table fails here."""
import re
from pathlib import Path

import pytest
import torch

from avatar_motor.body import rotations as rot

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"
TERM = re.compile(r"^([−-]?)\s*(\d+(?:\.\d+)?)?\s*([xyzw])$")


def _rows() -> dict[str, tuple[str, str]]:
    """engine -> (position conversion, quaternion conversion): the first parenthesised tuple of
    each of the table's last two columns."""
    rows = {}
    section = DOC.read_text().split("## Mapping to engines", 1)[1]
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and cells[0] in ("Unity", "Godot", "Unreal"):
            first = lambda c: re.search(r"\(([^()]*)\)", c).group(1)  # noqa: E731
            rows[cells[0]] = (first(cells[4]), first(cells[5]))
    return rows


def _linear(expr: str, variables: str) -> torch.Tensor:
    """'(−x, y, z)'-style components -> the matrix (len, len(variables)) of coefficients."""
    out = torch.zeros(len(expr.split(",")), len(variables), dtype=torch.float64)
    for i, term in enumerate(expr.split(",")):
        m = TERM.match(term.strip())
        assert m, f"cannot read {term!r} in {expr!r}"
        sign, scale, var = m.groups()
        out[i, variables.index(var)] = (-1.0 if sign else 1.0) * float(scale or 1.0)
    return out


def test_the_table_has_every_engine():
    assert set(_rows()) == {"Unity", "Godot", "Unreal"}


@pytest.mark.parametrize("engine", ["Unity", "Godot", "Unreal"])
def test_each_engines_quaternion_conversion_agrees_with_its_position_conversion(engine):
    pos, quat = _rows()[engine]
    M = _linear(pos, "xyz")
    M = M / M.abs().sum(1, keepdim=True)  # units aside (Unreal's centimetres)
    Q = _linear(quat, "xyzw")
    torch.manual_seed(0)
    q = rot.normalize(torch.randn(20, 4, dtype=torch.float64))  # (w, x, y, z)
    xyzw = torch.cat((q[:, 1:], q[:, :1]), 1)
    converted = xyzw @ Q.T
    R = rot.quat_to_matrix(q)
    R_engine = rot.quat_to_matrix(torch.cat((converted[:, 3:], converted[:, :3]), 1))
    v = torch.randn(20, 3, dtype=torch.float64)
    # the engine rotates the converted vector as we rotate ours, then converts
    assert torch.allclose(R_engine @ (v @ M.T)[..., None], ((R @ v[..., None])[..., 0] @ M.T)[..., None], atol=1e-9)
