"""Where an effect acts: on every body at once, on one body, or on one pair of contact parties (box on table, box on
box); and the model the diagnosis works on, in which each contact pair can carry its own parameters.

**Contact parties.** A moving body is a party (all its colliding geoms); a static geom is a party by its own name (a
table or floor in the world body), a static body other than the world by the body's name. A *contact pair* is two
parties that touch in the recordings: found by collision detection at the recorded states with a 5 mm margin.

**The prepared model.** MuJoCo mixes two geoms' parameters when they touch (friction: the larger; solref and solimp:
weighted by solmix; condim, margin and gap: the larger), so a contact pair has no parameters of its own, and changing
one geom's friction changes every contact that geom makes. When a scene has more than one moving body or contact pair
(and its MJCF is at hand), the diagnosis works on a copy in which every geom combination of every contact pair is an
explicit ``<pair>`` carrying the mixed values MuJoCo would have used (an explicit pair replaces the automatic contact
of those two geoms, so no contact is doubled) and every geom of a moving body uses MuJoCo's ellipsoid fluid model
(drag per body; no force while the medium density is zero). The copy is checked to simulate as the nominal model
does; if it does not, the nominal model is used and only body-level localisation is offered.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory

log = logging.getLogger(__name__)

DETECTION_MARGIN_M = 0.005
"""Recorded states are noisy: geoms this close count as touching when contact pairs are found."""
PREPARED_TOLERANCE = 1e-4
"""Largest position difference (m, or rad) after 0.1 s between the prepared and the nominal model from the same
recorded states; more means the explicit pairs do not reproduce MuJoCo's mixing (an unusual setting) and the
nominal model is used."""


@dataclass(frozen=True, kw_only=True)
class Target:
    """Where an effect acts: ``kind`` "all", "body" (``parties`` = the body) or "pair" (the two parties, sorted)."""

    kind: str = "all"
    parties: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """ "all", the body's name, or "a|b" for a contact pair."""
        return "all" if self.kind == "all" else "|".join(self.parties)

    def key(self, effect: str) -> str:
        """How the diagnosis names an effect acting here: ``effect``, ``effect@body`` or ``effect@a|b``."""
        return effect if self.kind == "all" else f"{effect}@{self.label}"

    def to_json(self) -> dict[str, object]:
        return {"kind": self.kind, "label": self.label, "parties": list(self.parties)}


ALL = Target()


def body_target(body: str) -> Target:
    return Target(kind="body", parties=(body,))


def pair_target(a: str, b: str) -> Target:
    return Target(kind="pair", parties=tuple(sorted((a, b))))


# ------------------------------------------------------------------------------------------------------ parties
def _name(model: mujoco.MjModel, obj: mujoco.mjtObj, index: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, obj, index) or f"{fallback}{index}"


def body_name(model: mujoco.MjModel, body: int) -> str:
    return _name(model, mujoco.mjtObj.mjOBJ_BODY, body, "body")


def party_of_geom(model: mujoco.MjModel, geom: int) -> str:
    """The contact party a geom belongs to (see the module docstring)."""
    body = int(model.geom_bodyid[geom])
    if body != 0:
        return body_name(model, body)
    return _name(model, mujoco.mjtObj.mjOBJ_GEOM, geom, "geom")


def contact_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Geoms that take part in collisions."""
    return np.flatnonzero((model.geom_contype != 0) | (model.geom_conaffinity != 0))


def moving_bodies(model: mujoco.MjModel) -> list[int]:
    """Bodies with at least one degree of freedom above them (not welded to the world)."""
    return [b for b in range(1, model.nbody) if model.body_weldid[b] != 0]


def party_geoms(model: mujoco.MjModel, party: str) -> np.ndarray:
    """Colliding geoms of a party (empty when the name is not one)."""
    return np.array([g for g in contact_geoms(model) if party_of_geom(model, int(g)) == party], dtype=np.int64)


def pair_rows(model: mujoco.MjModel, target: Target) -> np.ndarray:
    """Explicit ``<pair>`` rows a target acts on: every row for "all", rows with the body for "body", rows between
    the two parties for "pair"."""
    if model.npair == 0:
        return np.zeros(0, np.int64)
    if target.kind == "all":
        return np.arange(model.npair)
    rows = []
    for p in range(model.npair):
        parties = {party_of_geom(model, int(model.pair_geom1[p])), party_of_geom(model, int(model.pair_geom2[p]))}
        if (target.kind == "body" and target.parties[0] in parties) or (
            target.kind == "pair" and parties == set(target.parties)
        ):
            rows.append(p)
    return np.array(rows, np.int64)


def target_geoms(model: mujoco.MjModel, target: Target) -> np.ndarray:
    """Geoms whose own contact parameters a target changes: all colliding geoms, or the body's ("pair": none, the
    explicit pair rows carry it)."""
    if target.kind == "all":
        return contact_geoms(model)
    if target.kind == "body":
        return party_geoms(model, target.parties[0])
    return np.zeros(0, np.int64)


def moving_body_names(model: mujoco.MjModel) -> list[str]:
    return [body_name(model, b) for b in moving_bodies(model)]


def body_id(model: mujoco.MjModel, name: str) -> int:
    return int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name))


# ---------------------------------------------------------------------------------------------- contacts in data
def contacts_at_samples(model: mujoco.MjModel, traj: Trajectory) -> list[frozenset[tuple[str, str]]]:
    """Per recorded sample, the contact pairs (sorted party names) touching at the recorded state."""
    m = copy.copy(model)
    m.geom_margin[:] = np.maximum(m.geom_margin, DETECTION_MARGIN_M)
    data = mujoco.MjData(m)
    parties = {int(g): party_of_geom(model, int(g)) for g in contact_geoms(model)}
    out = []
    for k in range(traj.num_steps):
        data.qpos[:] = traj.qpos[k]
        mujoco.mj_kinematics(m, data)
        mujoco.mj_collision(m, data)
        found: set[tuple[str, str]] = set()
        for c in range(data.ncon):
            g1, g2 = int(data.contact.geom1[c]), int(data.contact.geom2[c])
            a, b = parties.get(g1), parties.get(g2)
            if a is None or b is None or a == b:
                continue
            found.add((a, b) if a < b else (b, a))
        out.append(frozenset(found))
    return out


@dataclass(frozen=True, kw_only=True)
class Layout:
    """The bodies and contact pairs of a scene as the recordings show them.

    Attributes:
        bodies: moving bodies (names), in tree order.
        pairs: contact pairs seen in the recordings (sorted party names), most samples first.
        pair_samples: samples in contact, per pair.
        explicit: the diagnosis model carries one ``<pair>`` per geom combination of each contact pair.
        fluid_per_body: every moving body's geoms use the ellipsoid fluid model (air drag per body possible).
    """

    bodies: tuple[str, ...]
    pairs: tuple[tuple[str, str], ...]
    pair_samples: dict[tuple[str, str], int] = field(default_factory=dict)
    explicit: bool = False
    fluid_per_body: bool = False

    @property
    def localised(self) -> bool:
        """Whether a body or pair differs from "all": more than one moving body or contact pair."""
        return len(self.bodies) > 1 or len(self.pairs) > 1


def find_layout(model: mujoco.MjModel, contacts: Sequence[list[frozenset[tuple[str, str]]]]) -> Layout:
    counts: dict[tuple[str, str], int] = {}
    for per_traj in contacts:
        for sample in per_traj:
            for pair in sample:
                counts[pair] = counts.get(pair, 0) + 1
    moving = set(moving_body_names(model))
    pairs = tuple(sorted((p for p in counts if moving & set(p)), key=lambda p: (-counts[p], p)))
    return Layout(bodies=tuple(moving_body_names(model)), pairs=pairs, pair_samples={p: counts[p] for p in pairs})


def possible_pairs(model: mujoco.MjModel) -> tuple[tuple[str, str], ...]:
    """Every pair of parties, at least one moving, with geoms that can collide (contype/conaffinity)."""
    geoms = contact_geoms(model)
    moving = set(moving_body_names(model))
    out: set[tuple[str, str]] = set()
    for i, g1 in enumerate(geoms):
        for g2 in geoms[i + 1 :]:
            a, b = party_of_geom(model, int(g1)), party_of_geom(model, int(g2))
            if a != b and (a in moving or b in moving) and _collide(model, int(g1), int(g2)):
                out.add((a, b) if a < b else (b, a))
    return tuple(sorted(out))


# ------------------------------------------------------------------------------------------- the prepared model
def _mix(model: mujoco.MjModel, g1: int, g2: int) -> dict[str, np.ndarray | float | int]:
    """The contact parameters MuJoCo uses for geoms g1 and g2 (its ``mj_contactParam``, without explicit pairs)."""
    p1, p2 = int(model.geom_priority[g1]), int(model.geom_priority[g2])
    if p1 != p2:
        g = g1 if p1 > p2 else g2
        fr = model.geom_friction[g]
        return {
            "condim": int(model.geom_condim[g]),
            "friction": np.array([fr[0], fr[0], fr[1], fr[2], fr[2]]),
            "solref": model.geom_solref[g].copy(),
            "solimp": model.geom_solimp[g].copy(),
            "margin": float(max(model.geom_margin[g1], model.geom_margin[g2])),
            "gap": float(max(model.geom_gap[g1], model.geom_gap[g2])),
        }
    s1, s2 = float(model.geom_solmix[g1]), float(model.geom_solmix[g2])
    tiny = mujoco.mjMINVAL
    if s1 < tiny and s2 < tiny:
        mix = 0.5
    elif s1 < tiny:
        mix = 0.0
    elif s2 < tiny:
        mix = 1.0
    else:
        mix = s1 / (s1 + s2)
    r1, r2 = model.geom_solref[g1], model.geom_solref[g2]
    solref = mix * r1 + (1 - mix) * r2 if (r1[0] > 0 and r2[0] > 0) else np.minimum(r1, r2)
    fr = np.maximum(model.geom_friction[g1], model.geom_friction[g2])
    return {
        "condim": int(max(model.geom_condim[g1], model.geom_condim[g2])),
        "friction": np.array([fr[0], fr[0], fr[1], fr[2], fr[2]]),
        "solref": np.asarray(solref, float),
        "solimp": mix * model.geom_solimp[g1] + (1 - mix) * model.geom_solimp[g2],
        "margin": float(max(model.geom_margin[g1], model.geom_margin[g2])),
        "gap": float(max(model.geom_gap[g1], model.geom_gap[g2])),
    }


def _collide(model: mujoco.MjModel, g1: int, g2: int) -> bool:
    return bool(
        (model.geom_contype[g1] & model.geom_conaffinity[g2]) or (model.geom_contype[g2] & model.geom_conaffinity[g1])
    )


def prepared_spec(spec: mujoco.MjSpec, model: mujoco.MjModel, layout: Layout) -> mujoco.MjSpec:
    """A copy of ``spec`` with one explicit pair per geom combination of each contact pair (mixed values) and, when
    the medium is still (density and viscosity zero), the ellipsoid fluid model on every moving body's geoms."""
    out = spec.copy()
    out.compile()  # assigns ids: spec geoms are listed in definition order, not in compiled order
    geoms = {int(g.id): g for g in out.geoms}
    for i, g in geoms.items():
        if not g.name:
            g.name = f"diag_geom{i}"
    for a, b in layout.pairs:
        for g1 in party_geoms(model, a):
            for g2 in party_geoms(model, b):
                if not _collide(model, int(g1), int(g2)):
                    continue
                mixed = _mix(model, int(g1), int(g2))
                out.add_pair(
                    geomname1=geoms[int(g1)].name,
                    geomname2=geoms[int(g2)].name,
                    condim=int(mixed["condim"]),
                    friction=mixed["friction"],
                    solref=mixed["solref"],
                    solimp=mixed["solimp"],
                    margin=float(mixed["margin"]),
                    gap=float(mixed["gap"]),
                )
    if model.opt.density == 0 and model.opt.viscosity == 0:
        moving = {b for b in range(1, model.nbody) if model.body_weldid[b] != 0}
        for i, g in geoms.items():
            if int(model.geom_bodyid[i]) in moving:
                g.fluid_ellipsoid = 1.0
    return out


def _same_motion(a: mujoco.MjModel, b: mujoco.MjModel, trajs: Sequence[Trajectory]) -> float:
    """Largest qpos difference after 0.1 s from a few recorded states, simulated by both models."""
    worst = 0.0
    steps = max(1, round(0.1 / a.opt.timestep))
    da, db = mujoco.MjData(a), mujoco.MjData(b)
    for traj in trajs[:4]:
        for k in np.linspace(0, traj.num_steps - 1, 4).astype(int):
            for m, d in ((a, da), (b, db)):
                mujoco.mj_resetData(m, d)
                d.qpos[:] = traj.qpos[k]
                d.qvel[:] = traj.qvel[k]
                mujoco.mj_step(m, d, nstep=steps)
            worst = max(worst, float(np.max(np.abs(da.qpos - db.qpos))))
    return worst


def prepare(
    model: mujoco.MjModel,
    spec: mujoco.MjSpec | None,
    trajs: Sequence[Trajectory],
    contacts: Sequence[list[frozenset[tuple[str, str]]]],
) -> tuple[mujoco.MjModel, Layout]:
    """The model the diagnosis works on and the scene's layout (``contacts``: `contacts_at_samples` of each
    trajectory); ``layout.explicit`` says whether contact pairs got their own parameters."""
    layout = find_layout(model, contacts)
    if spec is None or not layout.localised:
        return model, layout
    try:
        out_spec = prepared_spec(spec, model, layout)
        prepared = out_spec.compile()
    except Exception as exc:  # an MJCF feature the copy cannot carry: diagnose on the nominal model
        log.warning("could not give contact pairs their own parameters (%s); localising by body only", exc)
        return model, layout
    same = (prepared.nq, prepared.nv, prepared.nu, prepared.ngeom, prepared.nbody) == (
        model.nq,
        model.nv,
        model.nu,
        model.ngeom,
        model.nbody,
    )
    diff = _same_motion(model, prepared, trajs) if same else np.inf
    if not same or diff > PREPARED_TOLERANCE:
        log.warning(
            "explicit contact pairs do not reproduce the scene's contacts (%.3g after 0.1 s); localising by body only",
            diff,
        )
        return model, layout
    fluid = bool(prepared.opt.density == 0 and prepared.opt.viscosity == 0 and np.any(prepared.geom_fluid[:, 0] > 0))
    return prepared, replace(layout, explicit=True, fluid_per_body=fluid)
