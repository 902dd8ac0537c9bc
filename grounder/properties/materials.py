"""The material table behind the property model: real-world ranges of density, friction and restitution.

Every synthetic training object draws its material from `MATERIALS` and its properties uniformly (log-uniformly for
densities and contact lengths) inside that material's ranges. The ranges are for *tabletop objects as MuJoCo sees
them*: `density_kg_m3` is the effective (bulk) density, mass over the volume enclosed by the object's watertight
outer mesh, which is what `ground` multiplies by the mesh volume. For solid objects it is the material's density;
for closed hollow objects (a cardboard box, a drinks can, a stuffed toy) it is lower and says so in the notes.
Friction is the object sliding on a dry wooden or laminate table top (the object's contact parameters win in the
exported MJCF).

Sources (numbers are rounded and the ranges widened to cover common variants; a judgement, not a measurement):
- [ETB-wood]   The Engineering ToolBox, "Wood Species - Densities" (air-dry softwoods 350-600, hardwoods
               550-900 kg/m^3).
- [ETB-metal]  The Engineering ToolBox, "Metals and Alloys - Densities" (aluminium 2640-2810, steel 7750-8050,
               brass 8400-8730 kg/m^3).
- [ETB-plast]  The Engineering ToolBox, "Plastics - Densities" / CRC Handbook of Chemistry and Physics, 97th ed.,
               "Density of polymers" (PP 900, HDPE 950, ABS 1040-1060, PMMA 1180, PVC 1300-1450 kg/m^3).
- [ETB-rub]    The Engineering ToolBox, "Rubber - Densities" (natural rubber 930, neoprene 1230, silicone
               1100-1300 kg/m^3).
- [CRC-glass]  CRC Handbook, "Properties of glasses" (soda-lime 2440-2520, borosilicate 2230 kg/m^3).
- [ETB-ceram]  The Engineering ToolBox, "Solids - Densities" (porcelain 2300-2500, earthenware/stoneware
               1900-2400 kg/m^3).
- [ETB-foam]   The Engineering ToolBox, "Solids - Densities" (expanded polystyrene 15-35, polyurethane foam
               25-100 kg/m^3).
- [ETB-fric]   The Engineering ToolBox, "Friction and Friction Coefficients" (dry static/kinetic: wood-wood
               0.25-0.5, steel-wood 0.2-0.6, aluminium-wood ~0.3, rubber-dry surfaces 0.6-1.0+, glass on wood
               0.2-0.4, leather/fabric-wood 0.3-0.6, cardboard-wood ~0.4-0.5).
- [CRC-fric]   CRC Handbook of Chemistry and Physics, "Coefficient of friction" table (kinetic, dry).
- [ETB-roll]   The Engineering ToolBox, "Rolling Resistance" (coefficients 0.001-0.002 steel on steel up to
               0.01-0.03 rubber, scaled by contact radius to MuJoCo's rolling length in metres).
- [Cross99]    R. Cross, "The bounce of a ball", Am. J. Phys. 67 (1999) 222-227, and the coefficient-of-restitution
               tables summarised there (hard rubber/superball ~0.8-0.9, wood/hard plastic ~0.5-0.7, soft/damped
               objects < 0.3).
- [MuJoCo]     MuJoCo documentation, "Computation > Soft contacts": solref = (timeconst, dampratio); the reference
               acceleration is that of a mass-spring-damper with damping ratio dampratio, so a restitution e maps to
               dampratio = -ln(e) / sqrt(pi^2 + ln(e)^2) (and timeconst >= 2 x timestep).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class Material:
    """One row of the material table (ranges are (low, high), sampled uniformly unless the field says log).

    Attributes:
        name: class name (the model's auxiliary output).
        density_kg_m3: effective density range, sampled log-uniformly.
        sliding: sliding friction coefficient on a wooden table.
        contact_radius_m: contact patch radius (log-uniform); torsional friction = sliding x radius (MuJoCo's
            torsional coefficient is a length).
        rolling_m: rolling resistance length (log-uniform), MuJoCo's rolling coefficient.
        restitution: coefficient of restitution on a wooden table.
        timeconst_s: solref time constant (log-uniform): stiff materials short, soft ones long.
        shapes: shape kinds this material usually comes in, with weights (appearance and shape go together).
        sources: keys of the references in the module docstring.
        notes: what the effective density assumes.
    """

    name: str
    density_kg_m3: tuple[float, float]
    sliding: tuple[float, float]
    contact_radius_m: tuple[float, float]
    rolling_m: tuple[float, float]
    restitution: tuple[float, float]
    timeconst_s: tuple[float, float]
    shapes: dict[str, float]
    sources: tuple[str, ...]
    notes: str = "solid"


_ANY = {"box": 1.0, "cylinder": 1.0, "ellipsoid": 0.6, "capsule": 0.4, "bowl": 0.5, "cup": 0.5, "bottle": 0.4}


def _shapes(**weights: float) -> dict[str, float]:
    # Every material can take every shape (so the model cannot read the material off the shape alone), but
    # with realistic preferences.
    return {k: weights.get(k, 0.15 * v) for k, v in _ANY.items()}


MATERIALS: tuple[Material, ...] = (
    Material(
        name="wood",
        density_kg_m3=(350.0, 900.0),
        sliding=(0.25, 0.5),
        contact_radius_m=(0.001, 0.004),
        rolling_m=(2e-5, 2e-4),
        restitution=(0.4, 0.6),
        timeconst_s=(0.008, 0.02),
        shapes=_shapes(box=1.0, cylinder=0.8, ellipsoid=0.3, capsule=0.3, bowl=0.4),
        sources=("ETB-wood", "ETB-fric", "Cross99"),
    ),
    Material(
        name="metal",
        density_kg_m3=(2600.0, 8500.0),
        sliding=(0.2, 0.45),
        contact_radius_m=(0.0005, 0.002),
        rolling_m=(1e-5, 1e-4),
        restitution=(0.45, 0.7),
        timeconst_s=(0.005, 0.01),
        shapes=_shapes(box=0.6, cylinder=1.0, ellipsoid=0.3, capsule=0.5, cup=0.4, bowl=0.3),
        sources=("ETB-metal", "ETB-fric", "CRC-fric", "Cross99"),
    ),
    Material(
        name="metal_can",
        density_kg_m3=(250.0, 1100.0),
        sliding=(0.25, 0.45),
        contact_radius_m=(0.0005, 0.002),
        rolling_m=(1e-5, 1e-4),
        restitution=(0.1, 0.35),
        timeconst_s=(0.006, 0.015),
        shapes=_shapes(cylinder=1.0, box=0.2),
        sources=("ETB-metal", "ETB-fric"),
        notes="closed thin-walled metal container, from nearly empty to full of liquid (water 1000 kg/m^3)",
    ),
    Material(
        name="plastic",
        density_kg_m3=(880.0, 1450.0),
        sliding=(0.2, 0.45),
        contact_radius_m=(0.001, 0.003),
        rolling_m=(3e-5, 3e-4),
        restitution=(0.45, 0.7),
        timeconst_s=(0.008, 0.02),
        shapes=_shapes(box=0.8, cylinder=0.8, ellipsoid=0.5, capsule=0.5, cup=0.6, bottle=0.8, bowl=0.5),
        sources=("ETB-plast", "ETB-fric", "Cross99"),
    ),
    Material(
        name="rubber",
        density_kg_m3=(900.0, 1500.0),
        sliding=(0.7, 1.1),
        contact_radius_m=(0.002, 0.008),
        rolling_m=(2e-4, 2e-3),
        restitution=(0.6, 0.85),
        timeconst_s=(0.015, 0.03),
        shapes=_shapes(ellipsoid=1.0, cylinder=0.6, box=0.5, capsule=0.5),
        sources=("ETB-rub", "ETB-fric", "ETB-roll", "Cross99"),
    ),
    Material(
        name="glass",
        density_kg_m3=(2200.0, 2800.0),
        sliding=(0.2, 0.4),
        contact_radius_m=(0.0005, 0.0015),
        rolling_m=(1e-5, 1e-4),
        restitution=(0.5, 0.75),
        timeconst_s=(0.005, 0.01),
        shapes=_shapes(cylinder=0.8, cup=1.0, bowl=0.8, bottle=1.0),
        sources=("CRC-glass", "ETB-fric", "Cross99"),
    ),
    Material(
        name="ceramic",
        density_kg_m3=(1900.0, 2500.0),
        sliding=(0.35, 0.6),
        contact_radius_m=(0.0005, 0.002),
        rolling_m=(1e-5, 1e-4),
        restitution=(0.4, 0.65),
        timeconst_s=(0.005, 0.012),
        shapes=_shapes(bowl=1.0, cup=1.0, cylinder=0.5),
        sources=("ETB-ceram", "ETB-fric", "Cross99"),
    ),
    Material(
        name="cardboard",
        density_kg_m3=(50.0, 300.0),
        sliding=(0.4, 0.65),
        contact_radius_m=(0.002, 0.006),
        rolling_m=(3e-4, 2e-3),
        restitution=(0.1, 0.3),
        timeconst_s=(0.02, 0.05),
        shapes=_shapes(box=1.0, cylinder=0.3),
        sources=("ETB-fric",),
        notes="closed box or tube (board 600-800 kg/m^3 as walls, mostly air or light contents inside)",
    ),
    Material(
        name="foam",
        density_kg_m3=(15.0, 100.0),
        sliding=(0.5, 0.9),
        contact_radius_m=(0.004, 0.012),
        rolling_m=(1e-3, 5e-3),
        restitution=(0.05, 0.25),
        timeconst_s=(0.025, 0.06),
        shapes=_shapes(box=1.0, cylinder=0.6, ellipsoid=0.6),
        sources=("ETB-foam", "ETB-fric", "Cross99"),
    ),
    Material(
        name="fabric",
        density_kg_m3=(60.0, 400.0),
        sliding=(0.45, 0.75),
        contact_radius_m=(0.004, 0.012),
        rolling_m=(1e-3, 5e-3),
        restitution=(0.05, 0.2),
        timeconst_s=(0.025, 0.06),
        shapes=_shapes(ellipsoid=1.0, box=0.6, capsule=0.6, cylinder=0.4),
        sources=("ETB-fric", "Cross99"),
        notes="stuffed or folded textile (fibres ~1300-1500 kg/m^3, mostly air)",
    ),
)

MATERIAL_NAMES: tuple[str, ...] = tuple(m.name for m in MATERIALS)

# The model's regression targets, all on unbounded scales where a Gaussian is a fair description.
TARGET_NAMES: tuple[str, ...] = (
    "log_density",  # ln(kg/m^3)
    "log_sliding",  # ln(mu)
    "log_torsional_m",  # ln(m)
    "log_rolling_m",  # ln(m)
    "logit_restitution",  # ln(e / (1 - e))
    "log_timeconst_s",  # ln(s)
)


@dataclass(frozen=True, kw_only=True)
class PhysicalProperties:
    """Properties of one object, in MuJoCo's terms."""

    material: str
    density_kg_m3: float
    friction: tuple[float, float, float]  # sliding, torsional (m), rolling (m)
    restitution: float
    timeconst_s: float

    @property
    def solref(self) -> tuple[float, float]:
        """What a scene exported with the default settings writes: the time constant, raised to what the time step
        resolves, and the damping ratio that bounces at this restitution (`grounder.sim.restitution.contact_solref`)."""
        from grounder.sim.restitution import contact_solref

        return contact_solref(self.restitution, self.timeconst_s)

    def targets(self) -> np.ndarray:
        """(6,) the model's regression targets in `TARGET_NAMES` order."""
        e = self.restitution
        return np.array(
            [
                math.log(self.density_kg_m3),
                math.log(self.friction[0]),
                math.log(self.friction[1]),
                math.log(self.friction[2]),
                math.log(e / (1 - e)),
                math.log(self.timeconst_s),
            ]
        )


def sample_properties(material: Material, rng: np.random.Generator) -> PhysicalProperties:
    """Independent draws inside the material's ranges."""

    def loguniform(low_high: tuple[float, float]) -> float:
        return float(np.exp(rng.uniform(np.log(low_high[0]), np.log(low_high[1]))))

    sliding = float(rng.uniform(*material.sliding))
    return PhysicalProperties(
        material=material.name,
        density_kg_m3=loguniform(material.density_kg_m3),
        friction=(sliding, sliding * loguniform(material.contact_radius_m), loguniform(material.rolling_m)),
        restitution=float(rng.uniform(*material.restitution)),
        timeconst_s=loguniform(material.timeconst_s),
    )
