"""The sphere-cloth scene against the in-process engine: stable and bounded with the default and the stiff
settings, while the same cloth with the penalty integrated explicitly diverges at the stiff ones."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from badf.server._cloth import Cloth, ClothSettings, SphereMotion
from badf.server.adf import DistanceField

# Bounded: the sphere (speed about 1.3 m/s) cannot give the 1 kg cloth more than a few joules; a diverging
# integrator passes 1e3 J within a few frames.
MAX_KINETIC_ENERGY = 50.0
DIVERGED_KINETIC_ENERGY = 1e3


def _run(settings: ClothSettings, contact: str, frames: int):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rest, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces, np.int32)
    motion = SphereMotion(phase=0.12)  # the sphere reaches the cloth within the first second
    field = DistanceField(rest * motion.radius + motion.centre(0.0), faces, depth=4, device="cpu")
    cloth = Cloth(settings, contact=contact)

    def query(points):
        result = field.query(points, mode="adf", outputs=("distance", "normal"))
        return result.distance, result.normal

    reports = []
    for _ in range(frames):
        field.update(rest * motion.radius + motion.centre(cloth.time + settings.frame_time))
        reports.append(cloth.step(query))
        if not reports[-1].finite or reports[-1].kinetic_energy > DIVERGED_KINETIC_ENERGY:
            break
    return reports


@pytest.mark.parametrize("settings", [ClothSettings(), ClothSettings.stiff()], ids=["default", "stiff"])
def test_cloth_stays_finite_bounded_and_outside_the_sphere(settings):
    reports = _run(settings, "implicit", 75)
    assert len(reports) == 75 and all(r.finite for r in reports)
    assert max(r.kinetic_energy for r in reports) < MAX_KINETIC_ENERGY
    assert sum(r.contacts for r in reports) > 0  # the sphere did reach the cloth
    # penetration below a tenth of the sphere's radius on every frame
    assert max(r.penetration for r in reports) < 0.1 * SphereMotion().radius


def test_stiff_settings_break_an_explicit_penalty():
    assert ClothSettings.stiff().explicit_stability_number > 2.0 > ClothSettings().explicit_stability_number
    reports = _run(ClothSettings.stiff(), "explicit", 75)
    last = reports[-1]
    assert not last.finite or last.kinetic_energy > DIVERGED_KINETIC_ENERGY
