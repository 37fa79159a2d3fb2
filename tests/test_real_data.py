"""End to end on the real Bandai data (skipped when ../shared is absent): import, show, evaluate."""
import pytest

from avatar_motor.cli import main

from .conftest_models import SHIPPED


@pytest.mark.slow
def test_import_show_and_eval_realism_on_bandai(bandai, tmp_path, capsys, artifacts):
    assert main(["data", "import", str(bandai / "dataset-1" / "data"), "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "174 clips" in out and "content: walk 30" in out and "imported in" in out
    assert main(["data", "show", "dataset-1_kick_normal_001", "--frames", "0:90", "--png", str(artifacts / "bandai_kick.png")]) == 0
    assert (artifacts / "bandai_kick.png").stat().st_size > 10000
    assert main(["eval", "realism", "--model", str(SHIPPED), "--data", "dataset-1", "--n", "8", "--seconds", "4",
                 "--stability-seconds", "10", "--png", str(artifacts / "realism.png")]) == 0
    table = capsys.readouterr().out
    ancr = float(next(l for l in table.splitlines() if l.startswith("ANCR")).split()[2])
    assert ancr >= 0.99
    assert "no NaN True" in table
    join = float(next(l for l in table.splitlines() if l.startswith("join roughness")).split()[5])
    assert join > 0  # 8 x 4 s reads anywhere from 1.7 to 3.9: the figure is for 64 x 8 s
