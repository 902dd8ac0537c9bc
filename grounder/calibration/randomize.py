"""``image2sim randomize``: domain-randomisation variants of a calibrated scene, drawn from its fitted distribution.

Each variant is the scene's MJCF with the distribution's parameters set to one seeded draw (`MjSpec`, the same
setters calibration writes with). The folder holds ``variant_NNN.xml``, one copy of the files the scene loads
(meshes, textures) and ``variants.json`` (the values drawn per variant, the seed, the distribution's summary): the
same layout as ``image2sim properties sample``, which draws from the property model's prior instead.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from grounder.calibration.distribution import DISTRIBUTION_FILE, read_scene_distribution
from grounder.calibration.parameters import apply_to_spec
from grounder.errors import GrounderError

MAX_VARIANTS = 10000


def write_randomized_variants(scene: Path, out: Path, n: int, seed: int = 0, *, overwrite: bool = False) -> list[Path]:
    """Writes ``n`` variants of the calibrated scene folder ``scene`` into ``out`` (module docstring).

    Returns:
        The written MJCF paths; each loads with `mujoco.MjModel.from_xml_path`.

    Raises:
        GrounderError: ``scene`` has no ``distribution.json`` or it does not fit the scene, ``n`` is out of range, or
            ``out`` is not a new or empty folder (without ``overwrite``).
    """
    import mujoco

    from grounder.sim.scene_files import copy_scene_files, load_scene_spec, scene_xml_path
    from image2sim_common.outdir import check_output_dir, staged_output_dir

    if not 1 <= n <= MAX_VARIANTS:
        raise GrounderError(f"-n must be between 1 and {MAX_VARIANTS}, got {n}")
    scene = Path(scene)
    out = Path(out)
    check_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene,))
    xml_path = scene_xml_path(scene)
    scene_dir = xml_path.parent
    dist_path = scene_dir / DISTRIBUTION_FILE
    _, model = load_scene_spec(scene)
    dist = read_scene_distribution(
        scene_dir, model.nv, "(or draw from the property model's prior with `image2sim properties sample`)"
    )
    params = dist.parameters(model)
    values = dist.draw_values(params, n, np.random.default_rng(seed))
    paths = []
    record = []
    with staged_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene,)) as stage:
        copy_scene_files(xml_path, stage)  # one copy of the meshes and textures, shared by all variants
        for i, row in enumerate(values):
            spec = mujoco.MjSpec.from_file(str(xml_path))
            apply_to_spec(spec, model, params, row)
            try:
                spec.compile()
            except ValueError as exc:
                raise GrounderError(
                    f"variant {i} drawn from {dist_path} does not compile ({' '.join(str(exc).split())}); "
                    "re-run calibrate --distribution with narrower --params bounds"
                ) from exc
            name = f"variant_{i:03d}.xml"
            (stage / name).write_text(spec.to_xml())
            paths.append(out / name)
            record.append({"xml": name, "parameters": {p.name: float(v) for p, v in zip(params, row, strict=True)}})
        manifest = {
            "scene": str(scene),
            "distribution": str(dist_path),
            "seed": seed,
            "summary": dist.summary(params),
            "variants": record,
        }
        (stage / "variants.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return paths
