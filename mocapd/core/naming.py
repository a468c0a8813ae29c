"""Joint naming conventions of recorded motion, and which source joint plays each anatomical role.

Retargeting (:mod:`mocapd.core.retarget`) needs eleven roles from a source skeleton: the hips, the base of the
neck, the head and, per side, shoulder, elbow, wrist, hip, knee, ankle and toe (the toe may be missing: the
ankle's end site stands in), plus an optional hand tip. Every convention below is a complete table of those roles;
a file is matched against the conventions one at a time (never a mix of two), because the same name means
different joints in different conventions: ``LeftShoulder`` is the clavicle for Mixamo/HumanIK but the upper arm
in an MVN BVH export; ``left_foot`` is the toe in SMPL but ``LeftFoot`` the ankle elsewhere.

Names are compared lower-case after removing a namespace (``mixamorig:Hips`` → ``hips``, a Maya path
``a|b|Hips`` → ``hips``) and a prefix every joint shares up to an underscore (MotionBuilder's ``Character1_``,
SMPL's ``m_avg_``). In a pattern, ``{s}`` is ``left``/``right`` and ``{c}`` is ``l``/``r``.

Conventions (the joints each one needs are in :data:`CONVENTIONS`):

* ``autodesk``: CMU BVH (fairmotion), Mixamo (``mixamorig:`` prefix), MotionBuilder HumanIK (``Character1_``).
* ``mvn``: Xsens MVN segment names (MVNX ``LeftUpperArm``…) and MVN BVH exports (``LeftShoulder`` = upper arm,
  ``LeftElbow``…), also used by CMU's 131 BVH trials.
* ``bandai``: Bandai Namco (``UpperArm_L``).
* ``cmu_asf``: CMU ASF/AMC (``lhumerus``, ``lradius``…).
* ``daz_poser``: DAZ Studio / Poser, as in the widely used CMU conversions (``hip``, ``abdomen``, ``chest``,
  ``lShldr``, ``lForeArm``, ``lThigh``, ``lShin``; Genesis ``lShldrBend``…).
* ``smpl``: SMPL's 24 joints (``pelvis``, ``left_hip``… or ``Pelvis``, ``L_Hip``…).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from mocapd.errors import InputError

CENTRE_ROLES = ("hips", "neck_base", "head")
"""Roles without a side."""
SIDE_ROLES = ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
"""Roles needed on each side (``l`` and ``r``)."""
OPTIONAL_SIDE_ROLES = ("toe", "hand_tip")
"""Roles used when present; without a toe joint the ankle's end site is the toe."""

Table = dict[str, tuple[str, ...]]

CONVENTIONS: dict[str, Table] = {
    "autodesk": {
        "hips": ("hips",),
        "neck_base": ("lowerneck", "neck"),
        "head": ("head",),
        "shoulder": ("{s}arm",),
        "elbow": ("{s}forearm",),
        "wrist": ("{s}hand",),
        "hand_tip": ("{c}fingers", "{s}handfingers", "{s}handmiddle1"),
        "hip": ("{s}upleg",),
        "knee": ("{s}leg",),
        "ankle": ("{s}foot",),
        "toe": ("{s}toebase",),
    },
    "mvn": {
        "hips": ("pelvis", "hips"),
        "neck_base": ("lowerneck", "neck"),
        "head": ("head",),
        "shoulder": ("{s}upperarm", "{s}shoulder"),
        "elbow": ("{s}forearm", "{s}elbow"),
        "wrist": ("{s}hand", "{s}wrist"),
        "hand_tip": ("{c}fingers", "{s}handfingers"),
        "hip": ("{s}upperleg", "{s}hip"),
        "knee": ("{s}lowerleg", "{s}knee"),
        "ankle": ("{s}foot", "{s}ankle"),
        "toe": ("{s}toe", "{s}toes"),
    },
    "bandai": {
        "hips": ("hips",),
        "neck_base": ("neck",),
        "head": ("head",),
        "shoulder": ("upperarm_{c}",),
        "elbow": ("lowerarm_{c}",),
        "wrist": ("hand_{c}",),
        "hand_tip": (),
        "hip": ("upperleg_{c}",),
        "knee": ("lowerleg_{c}",),
        "ankle": ("foot_{c}",),
        "toe": ("toes_{c}",),
    },
    "cmu_asf": {
        "hips": ("root",),
        "neck_base": ("lowerneck",),
        "head": ("head",),
        "shoulder": ("{c}humerus",),
        "elbow": ("{c}radius",),
        "wrist": ("{c}wrist",),
        "hand_tip": ("{c}fingers",),
        "hip": ("{c}femur",),
        "knee": ("{c}tibia",),
        "ankle": ("{c}foot",),
        "toe": ("{c}toes",),
    },
    "daz_poser": {
        "hips": ("hip",),
        "neck_base": ("neck", "necklower"),
        "head": ("head",),
        "shoulder": ("{c}shldr", "{c}shldrbend"),
        "elbow": ("{c}forearm", "{c}forearmbend"),
        "wrist": ("{c}hand",),
        "hand_tip": ("{c}mid1",),
        "hip": ("{c}thigh", "{c}thighbend"),
        "knee": ("{c}shin",),
        "ankle": ("{c}foot",),
        "toe": ("{c}toe", "{c}toes"),
    },
    "smpl": {
        "hips": ("pelvis",),
        "neck_base": ("neck",),
        "head": ("head",),
        "shoulder": ("{s}_shoulder", "{c}_shoulder"),
        "elbow": ("{s}_elbow", "{c}_elbow"),
        "wrist": ("{s}_wrist", "{c}_wrist"),
        "hand_tip": ("{s}_hand", "{c}_hand"),
        "hip": ("{s}_hip", "{c}_hip"),
        "knee": ("{s}_knee", "{c}_knee"),
        "ankle": ("{s}_ankle", "{c}_ankle"),
        "toe": ("{s}_foot", "{c}_foot"),
    },
}
"""Role tables, tried in this order."""


@dataclass(frozen=True)
class RoleMatch:
    """The source joints of one naming convention.

    Attributes
    ----------
    convention : str
        Key of :data:`CONVENTIONS`.
    joints : dict of str to int
        Joint index per role: ``hips``, ``neck_base``, ``head`` and ``l``/``r`` + side role (``lshoulder``…);
        optional roles (``ltoe``, ``lhand_tip``…) only when the file has them.
    """

    convention: str
    joints: dict[str, int]


def normalized_names(names: Sequence[str]) -> list[str]:
    """Joint names lower-cased, without namespaces, paths or a prefix all of them share (see the module doc)."""
    bare = [n.rsplit("|", 1)[-1].rsplit(":", 1)[-1] for n in names]
    if len(bare) > 1:
        common = bare[0]
        for n in bare[1:]:
            k = 0
            while k < min(len(common), len(n)) and common[k] == n[k]:
                k += 1
            common = common[:k]
        cut = common.rfind("_") + 1  # only up to an underscore: "LeftArm"/"LeftLeg" share "Left", not a prefix
        if cut > 0 and all(len(n) > cut for n in bare):
            bare = [n[cut:] for n in bare]
    return [n.lower() for n in bare]


def _pattern(pat: str, side: str | None) -> str:
    if side is None:
        return pat
    return pat.format(s="left" if side == "l" else "right", c=side)


def _match(low: dict[str, int], table: Table) -> tuple[dict[str, int], list[str]]:
    """Joint per role found in ``low`` (name → index), and the roles missing (as the first name expected)."""
    found: dict[str, int] = {}
    missing: list[str] = []
    wanted = [(r, None) for r in CENTRE_ROLES] + [(r, s) for s in "lr" for r in SIDE_ROLES + OPTIONAL_SIDE_ROLES]
    for role, side in wanted:
        key = role if side is None else side + role
        hit = next((low[_pattern(p, side)] for p in table[role] if _pattern(p, side) in low), None)
        if hit is not None:
            found[key] = hit
        elif role not in OPTIONAL_SIDE_ROLES:
            missing.append(_pattern(table[role][0], side))
    return found, missing


def match_roles(names: Sequence[str], clip: str = "motion") -> RoleMatch:
    """The first convention of :data:`CONVENTIONS` that names every required role.

    Raises
    ------
    InputError
        When none does; the message lists, per convention, the joints it expected and did not find.
    """
    low: dict[str, int] = {}
    for i, n in enumerate(normalized_names(names)):
        low.setdefault(n, i)
    report = []
    for conv, table in CONVENTIONS.items():
        found, missing = _match(low, table)
        if not missing:
            return RoleMatch(conv, found)
        report.append(f"{conv} lacks {', '.join(missing)}")
    raise InputError(
        f"retarget {clip!r}: the joint names match no known naming convention ({'; '.join(report)}); "
        f"the file's joints: {', '.join(names)}"
    )


__all__ = ["CONVENTIONS", "RoleMatch", "match_roles", "normalized_names"]
