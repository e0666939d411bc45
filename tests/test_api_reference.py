"""The API reference (docs/api.md): pdoc builds it from the docstrings with the module list that docs/api.md gives,
and every public name, every field of the state and model classes, and every public member of the classes that
``kamino`` exports, has a docstring."""

from __future__ import annotations

import dataclasses
import re
import shlex
from pathlib import Path

import pytest

import kamino

# the test extra's (pyproject.toml), which CI installs; a machine without it (the GPU runner) skips this module
pytest.importorskip("pdoc")
import pdoc
import pdoc.doc

ROOT = Path(__file__).resolve().parents[1]
API_DOC = ROOT / "docs" / "api.md"


def _modules() -> list[str]:
    """The modules of docs/api.md's pdoc command."""
    commands = [line for block in re.findall(r"```bash\n(.*?)```", API_DOC.read_text(), re.S)
                for line in block.splitlines() if re.search(r"(^|\s)pdoc\s", line)]
    assert len(commands) == 1, commands
    words = shlex.split(commands[0])
    words = words[words.index("pdoc") + 1:]
    return words[:words.index("-o")]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, dict[str, pdoc.doc.Module]]:
    """The reference built into a temporary folder, and pdoc's view of each module."""
    out = tmp_path_factory.mktemp("api")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PDOC_ALLOW_EXEC", "1")  # brax's import of glfw runs a subprocess (docs/api.md)
        modules = _modules()
        pdoc.pdoc(*modules, output_directory=out)
        docs = {name: pdoc.doc.Module.from_name(name) for name in modules}
        for module in list(docs.values()):  # the submodules a module's __all__ names (kamino.models)
            for sub in module.submodules:
                if sub.name in module.obj.__all__:
                    docs[sub.modulename] = sub
        return out, docs


def _page(out: Path, module: str) -> str:
    return (out / (module.replace(".", "/") + ".html")).read_text()


def test_the_reference_covers_the_package_and_its_public_subpackages(reference):
    out, docs = reference
    assert _modules()[0] == "kamino"
    for name in ("kamino.models", "kamino.io", "kamino.viz", "kamino.plots", "kamino.sharding", "kamino.envs",
                 "kamino.envs.geometry"):
        assert name in docs and (out / (name.replace(".", "/") + ".html")).is_file(), name


def test_every_public_name_has_a_page_entry_and_a_docstring(reference):
    out, docs = reference
    missing = []
    for name, module in docs.items():
        page = _page(out, name)
        assert module.docstring.strip(), f"{name} has no module docstring"
        submodules = {m.name for m in module.submodules}
        for public in module.obj.__all__:
            if public in submodules:  # kamino.models: its own page
                assert (out / name.replace(".", "/") / f"{public}.html").is_file()
                continue
            member = module.members.get(public)
            if member is None or not member.docstring.strip():
                missing.append(f"{name}.{public}")
            assert f'id="{public}"' in page, f"{name}.{public} is not on its page"
    assert not missing, f"public names without a docstring: {missing}"


def _kamino_members(cls: pdoc.doc.Class) -> dict[str, pdoc.doc.Doc]:
    """The public members kamino defines on ``cls`` (not those inherited from int, enum or object)."""
    return {name: member for name, member in cls.members.items()
            if not name.startswith("_") and member.taken_from[0].startswith("kamino")}


def test_every_member_of_kamino_s_classes_has_a_docstring(reference):
    out, docs = reference
    top = docs["kamino"]
    page = _page(out, "kamino")
    missing = []
    classes = [member for member in top.members.values() if isinstance(member, pdoc.doc.Class)]
    assert {c.name for c in classes} >= {"Model", "State", "ContactState", "StepInfo", "Control", "SolverConfig",
                                         "ModelBuilder", "Actuation", "JointType", "GeomType", "ActuationMode",
                                         "FKResult", "IKResult", "Stabilisation", "Penalty", "WarpSettings"}
    for cls in classes:
        for name, member in _kamino_members(cls).items():
            if not member.docstring.strip():
                missing.append(f"{cls.name}.{name}")
            assert f'id="{cls.name}.{name}"' in page, f"{cls.name}.{name} is not on kamino's page"
    assert not missing, f"members without a docstring: {missing}"


@pytest.mark.parametrize("cls", [kamino.Model, kamino.State, kamino.ContactState, kamino.StepInfo, kamino.Control,
                                 kamino.SolverConfig, kamino.Stabilisation, kamino.Penalty, kamino.WarpSettings,
                                 kamino.FKResult, kamino.IKResult], ids=lambda c: c.__name__)
def test_every_field_is_documented(reference, cls):
    _, docs = reference
    members = docs["kamino"].members[cls.__name__].members
    fields = [f.name for f in dataclasses.fields(cls)]
    undocumented = [f for f in fields if f not in members or not members[f].docstring.strip()]
    assert not undocumented, f"{cls.__name__} fields without a docstring: {undocumented}"


def test_the_read_outs_a_task_needs_are_documented(reference):
    _, docs = reference
    for name in ("joint_positions", "joint_coordinates", "body_frame", "body_contact_forces", "dof_state"):
        assert name in kamino.__all__ and docs["kamino"].members[name].docstring.strip()
    geometry = docs["kamino.envs.geometry"]
    for name in ("body_frame_vectors", "support_points", "ground_height", "place_on_ground"):
        assert geometry.members[name].docstring.strip(), name
