"""The benchmark scenes ship with the package: ``kamino.bench.scene_path`` finds each by name, names the scenes when
asked for one that is not there, and the ladders are what ``kamino.bench.ladder_mjcf`` generates."""

import pytest

import kamino
from kamino.bench import scene_names, scene_path
from kamino.bench.ladder_mjcf import ladder_mjcf
from kamino.bench.ladder_mjcf import main as ladder_main

SCENES = ("biped_connect", "fourbar", "fourbar_connect", "humanoid10", "ladder32", "ladder8")


def test_scene_path_finds_every_shipped_scene_with_or_without_xml():
    assert scene_names() == sorted(SCENES)
    for name in SCENES:
        path = scene_path(name)
        assert path.is_file() and path.name == f"{name}.xml" and path.parent.name == "scenes"
        assert scene_path(f"{name}.xml") == path
    assert scene_path("fourbar").parent.parent.name == "bench"  # inside the package, not a checkout's benchmarks/


@pytest.mark.parametrize("name", ["nosuch", "", "../bench/cli", "scenes/fourbar"])
def test_scene_path_names_the_scenes_for_an_unknown_one(name):
    with pytest.raises(ValueError, match="no benchmark scene") as err:
        scene_path(name)
    assert all(s in str(err.value) for s in SCENES)


@pytest.mark.parametrize("loops", [8, 32])
def test_the_shipped_ladders_are_the_generated_ones(loops):
    """``ladder_mjcf(K)`` is the shipped ``ladderK.xml`` byte for byte, and loads as K loops: per loop 3 moving
    bodies (two rails and a rung; the top rung is welded to the world), 3 hinges of 5 rows and one ``<connect>`` of
    3 rows."""
    text = ladder_mjcf(loops)
    assert text == scene_path(f"ladder{loops}").read_text()
    model = kamino.load_mjcf(text)
    assert model.num_bodies == 3 * loops and model.num_joints == 4 * loops
    assert model.num_constraints == (3 * 5 + 3) * loops


def test_ladder_command_writes_the_file(tmp_path, capsys):
    assert ladder_main(["3", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "ladder3.xml").read_text() == ladder_mjcf(3)
    assert capsys.readouterr().out.strip() == str(tmp_path / "ladder3.xml")
    with pytest.raises(ValueError, match="positive integer"):
        ladder_mjcf(0)
    with pytest.raises(SystemExit):
        ladder_main(["0"])
