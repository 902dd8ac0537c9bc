"""A scene's files: where its MJCF is (a file, or ``scene.xml`` in a scene folder), the files it includes or loads
(checked to stay inside its folder), copying them into an output folder, and loading the scene as a compiled model
(`load_scene_model`) or as an editable `MjSpec` with its model (`load_scene_spec`). Shared by simulation,
calibration, the residual, the property prior, tracking and interaction.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import mujoco

from grounder.errors import GrounderError

SCENE_XML = "scene.xml"


def scene_xml_path(scene: Path) -> Path:
    """The MJCF of a scene given as a file or as a scene folder (``scene.xml`` inside), checked to keep every file
    it includes or loads inside its own folder (`scene_files`).

    Raises:
        GrounderError: neither exists, or the MJCF reaches outside its folder.
    """
    scene = Path(scene)
    if scene.is_dir():
        xml = scene / SCENE_XML
        if not xml.is_file():
            raise GrounderError(
                f"{scene}: scene folder has no {SCENE_XML}; pass an MJCF file or a scene folder (`image2sim ground`)"
            )
    elif not scene.is_file():
        raise GrounderError(
            f"{scene}: scene does not exist; pass an MJCF file or a scene folder with {SCENE_XML} (`image2sim ground`)"
        )
    elif scene.suffix.lower() == ".json":  # scene.json is the manifest beside the MJCF, not a scene
        raise GrounderError(
            f"{scene}: a JSON file, not an MJCF scene; pass the scene folder ({scene.parent}) or its {SCENE_XML}"
        )
    else:
        xml = scene
    scene_files(xml)
    return xml


_READ_WHILE_PARSING = ("include", "model", "flexcomp")  # MJCF elements whose file MuJoCo reads as it parses


def scene_files(xml: Path) -> list[Path]:
    """The files an MJCF includes or loads (included and attached MJCF, meshes, flexcomp meshes, textures, height
    fields, skins), each as a path relative to the MJCF's folder, checked to lie inside that folder.

    A scene is self-contained: it may be someone else's file, and what it names is read, and copied into the
    outputs of `calibrate` and `residual train`. A path that leaves the folder (``../``, an absolute path, or a link
    that resolves outside) is refused rather than followed. An MJCF that parses as XML but not as MJCF is left to
    the loader, which reports MuJoCo's own message.

    Raises:
        GrounderError: a file named by the MJCF lies outside its folder, or the MJCF is not well-formed XML.
    """
    import xml.etree.ElementTree as ET  # expat >= 2.4.1 refuses entity expansion attacks; no external entities

    folder = xml.parent.resolve()

    def inside(name: str, base: str = "") -> Path:
        target = (xml.parent / base / name).resolve()  # MuJoCo: relative to the main MJCF's folder (or its *dir)
        if not target.is_relative_to(folder):
            raise GrounderError(
                f"{xml}: it names {Path(base) / name} ({target}), outside the scene's folder {folder}; "
                "put every file the scene uses inside its folder (scenes may not read or write elsewhere)"
            )
        return target.relative_to(folder)

    # MuJoCo reads some files while it parses, before a spec exists to list them: <include>d MJCF, <model> assets
    # (attached MJCF) and <flexcomp> meshes. Those are found in the XML itself (and in each MJCF it pulls in), so
    # each is checked before MuJoCo reads it; an XML that does not parse as XML cannot be checked, and is refused
    # (MuJoCo's own parser accepts some that expat does not, such as an undefined entity).
    files: list[Path] = []
    pending, seen, meshdir = [xml.resolve()], set(), ""
    while pending:
        current = pending.pop()
        seen.add(current)
        try:
            tree = ET.parse(current)
        except ET.ParseError as exc:
            raise GrounderError(
                f"{current}: not well-formed XML ({exc}); fix it (a scene's files are checked in its XML before "
                "MuJoCo reads them)"
            ) from exc
        except OSError:
            continue  # a missing include: MuJoCo's loader names it
        for compiler in tree.iter("compiler"):
            meshdir = compiler.get("meshdir", compiler.get("assetdir", meshdir))
        for element in tree.iter():
            name = element.get("file", "")
            if not name or element.tag not in _READ_WHILE_PARSING:
                continue
            rel = inside(name, meshdir if element.tag == "flexcomp" else "")
            files.append(rel)
            if element.tag != "flexcomp" and (folder / rel) not in seen and (folder / rel).is_file():
                pending.append(folder / rel)
    try:
        spec = mujoco.MjSpec.from_file(str(xml))
    except ValueError:
        return files  # the loader reports it
    groups = (
        (spec.meshes, spec.meshdir),
        (spec.textures, spec.texturedir),
        (spec.hfields, spec.meshdir),
        (spec.skins, spec.meshdir),
    )
    for elements, base in groups:
        for element in elements:
            names = [getattr(element, "file", "")] + [str(n) for n in getattr(element, "cubefiles", [])]
            files.extend(inside(name, base or "") for name in names if name)
    return files


def check_links_stay_inside(scene: Path, skip: Sequence[str] = ()) -> None:
    """Refuses a link in a scene folder whose copy (`copy_scene_files`) would lead out of the output folder: an
    absolute link, or a relative one that resolves outside the scene folder. A later write to its name in the output
    would land in the link's target, a file of the user's. Commands call it before their work, and the copy again.

    Raises:
        GrounderError: naming the link and what to do.
    """
    if not scene.is_dir():
        return
    top = scene.resolve()
    for folder, dirs, names in os.walk(scene):  # links to folders are listed in dirs, and not followed
        at_top = Path(folder).resolve() == top
        for name in [*dirs, *names]:
            path = Path(folder) / name
            if (at_top and name in skip) or not path.is_symlink():
                continue
            if os.path.isabs(os.readlink(path)) or not path.resolve().is_relative_to(top):
                raise GrounderError(
                    f"{path}: a link to {os.readlink(path)}, which its copy would follow out of the output folder; "
                    "replace it with the file it points to, or a link relative to the scene folder"
                )


def copy_scene_files(scene: Path, stage: Path, *, skip: Sequence[str] = ()) -> None:
    """Copies what a scene's MJCF needs into ``stage``, at the same relative paths: a scene folder's files (not
    the top-level entries named in ``skip``, not ``stage`` itself when it lies inside the folder; links are copied
    as links; one that would lead out of the copy is refused), or a lone MJCF's included and loaded files
    (`scene_files`) and nothing else of its folder. The MJCF itself is left to the caller, which writes its own
    ``scene.xml``.
    """
    from image2sim_common.outdir import is_bookkeeping_name  # here: importing `reconstruction` loads pycolmap

    stage_resolved, top = stage.resolve(), scene.resolve()
    if scene.is_dir():

        def ignore(folder: str, names: list[str]) -> list[str]:
            at_top = Path(folder).resolve() == top
            return [
                n
                for n in names
                if (at_top and n in skip)
                or (Path(folder) / n).resolve() == stage_resolved
                or is_bookkeeping_name(n)  # the claim and staging of an output being written inside the folder
            ]

        check_links_stay_inside(scene, skip)
        shutil.copytree(scene, stage, symlinks=True, ignore=ignore, dirs_exist_ok=True)
        return
    for rel in scene_files(scene):
        dst = stage / rel
        if not dst.resolve().is_relative_to(stage_resolved):  # scene_files keeps rel inside; never write elsewhere
            raise GrounderError(f"{scene}: {rel} would be copied outside the output folder {stage}")
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(scene.parent / rel, dst)


def load_scene_model(scene: Path) -> tuple[Path, mujoco.MjModel]:
    """The scene's MJCF path and compiled model; `scene` is an MJCF file or a scene folder.

    Raises:
        GrounderError: missing file, or one MuJoCo cannot parse or compile (its message on one line).
    """
    xml = scene_xml_path(scene)
    try:
        return xml, mujoco.MjModel.from_xml_path(str(xml))
    except ValueError as exc:  # mujoco raises ValueError for parse and compile errors
        raise _cannot_load(xml, exc) from exc


def load_scene_spec(scene: Path) -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    """The scene's `MjSpec` and compiled model (what calibration edits and writes back as ``scene.xml``); `scene` is
    an MJCF file or a scene folder.

    Raises:
        GrounderError: missing or unreadable MJCF.
    """
    xml = scene_xml_path(scene)
    try:
        spec = mujoco.MjSpec.from_file(str(xml))
        model = spec.compile()
    except Exception as exc:  # mujoco raises ValueError for parse and compile errors
        raise _cannot_load(xml, exc) from exc
    return spec, model


def _cannot_load(xml: Path, exc: Exception) -> GrounderError:
    """MuJoCo's parse or compile error for ``xml``, on one line."""
    return GrounderError(f"{xml}: MuJoCo cannot load it ({' '.join(str(exc).split())})")
