import pytest

from avatar_motor.cli import build_parser, main


@pytest.mark.parametrize("cmd", [["train"], ["adapt"], ["distill"], ["data", "import"], ["data", "show"], ["data", "list"], ["generate"], ["serve"],
                                 ["eval", "realism"], ["eval", "control"], ["eval", "impulses"], ["bench"]])
def test_every_command_has_help(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(cmd + ["--help"])
    assert e.value.code == 0 and "usage: avatar-motor" in capsys.readouterr().out


def test_clear_errors_for_missing_things(tmp_path, capsys):
    assert main(["train", "--set", "steps=1", "--set", f"out={tmp_path / 'r'}", "--set", "data=[\"no-such-cache\"]"]) == 2
    assert "data import" in capsys.readouterr().err
    assert main(["train", "--config", str(tmp_path / "missing.json")]) == 2
    assert "cannot read the config" in capsys.readouterr().err
    assert main(["train", "--set", "stepz=1"]) == 2
    assert "unknown fields ['stepz']" in capsys.readouterr().err
    assert main(["adapt", "--set", "segment.x=1"]) == 2
    assert main(["generate", "--model", str(tmp_path / "nope"), "--out", str(tmp_path / "x.bvh")]) == 2
    assert "no such checkpoint folder" in capsys.readouterr().err
    assert main(["generate", "--out", str(tmp_path / "x.txt")]) == 2
    assert "use a .bvh, .glb, .npz or .fbx" in capsys.readouterr().err
    assert main(["data", "import", str(tmp_path / "missing")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["data", "list"]) == 0


def test_eval_impulses_reports_unpushed_acrobatics_and_draws_each_preset(tmp_path, capsys):
    from avatar_motor.runtime.crowd import IMPULSE_PRESETS
    from .conftest_models import tiny_motor
    tiny_motor(tmp_path)
    assert main(["eval", "impulses", "--model", str(tmp_path / "tiny"), "--n", "2", "--seconds", "1",
                 "--png", str(tmp_path / "imp.png")]) == 0
    out = capsys.readouterr().out
    rows = [line.split()[0] for line in out.splitlines() if line.split() and line.split()[0] in ("none", *IMPULSE_PRESETS)]
    assert rows == ["none", *IMPULSE_PRESETS]
    for preset in rows:
        assert (tmp_path / f"imp_{preset}.png").stat().st_size > 1000


def test_physics_scene_options_parse_and_name_what_is_wrong():
    from avatar_motor.cli import _parse_ball, _parse_obstacle, _parse_tilt
    assert _parse_ball("0,1.3,3:0,0,-10:2") == ([0.0, 1.3, 3.0], [0.0, 0.0, -10.0], 2.0)
    assert _parse_ball("0,1.3,3:0,0,-10") == ([0.0, 1.3, 3.0], [0.0, 0.0, -10.0], 1.0)  # 1 kg by default
    assert _parse_obstacle("0,1.5:2,0.2,0.15:30") == ([0.0, 1.5], [2.0, 0.2, 0.15], 30.0)
    assert _parse_obstacle("0,1.5:2,0.2,0.15") == ([0.0, 1.5], [2.0, 0.2, 0.15], 0.0)
    assert _parse_tilt("10,0") == ([10.0, 0.0], [0.0, 0.0])
    assert _parse_tilt("10,0:0,2") == ([10.0, 0.0], [0.0, 2.0])
    for parse, text, message in ((_parse_ball, "0,1.3,3", "use X,Y,Z:VX,VY,VZ"), (_parse_ball, "0,1.3:0,0,-10", "position"),
                                 (_parse_ball, "0,1,3:0,0,-10:heavy", "mass"), (_parse_obstacle, "0,1.5:2,0.2", "size"),
                                 (_parse_obstacle, "0,1.5:2,0.2,0.1:0:9", "use X,Z:SX,SY,SZ"), (_parse_tilt, "10", "tilt"),
                                 (_parse_tilt, "10,0:0,2:1", "use AX,AZ")):
        with pytest.raises(ValueError, match=message):
            parse(text)
