"""The paper's sphere-cloth scene: a cloth hanging from two corners, a sphere moving back and forth through it.

The client side of the demo, numpy only. The cloth is a grid of particles held by distance constraints
(stretch, shear, bend), projected with XPBD (Macklin et al. 2016) in Gauss-Seidel colour groups. Contact
with the sphere is a penalty force from one batched distance query per frame: a particle closer to the
sphere than the cloth's thickness is pushed out along the field's normal, with the penalty spring
integrated implicitly along that normal, so any stiffness and time step stay stable. The same cloth with
the penalty integrated explicitly (contact="explicit", kept for comparison) is stable at the default
settings and diverges at the `stiff` ones.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

GRAVITY = np.array([0.0, 0.0, -9.81])

# A distance query: (P, 3) points -> (signed distances (P,), unit normals (P, 3)) of the sphere's field.
DistanceQuery = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class ClothSettings:
    """Units: metres, kilograms, seconds, newtons per metre."""

    resolution: int = 91  # particles per side: 91 x 91 gives 16,200 triangles
    size: float = 2.0  # side of the square cloth
    mass: float = 1.0  # of the whole cloth
    thickness: float = 0.02  # contact distance from the sphere's surface
    penalty_stiffness: float = 6.0  # per particle; explicit Euler of it is stable at the default step
    penalty_damping: float = 0.02  # N s / m per particle
    frame_time: float = 1.0 / 60.0
    substeps: int = 2
    iterations: int = 6  # constraint projections per substep
    stretch_compliance: float = 1e-8  # m / N (XPBD alpha): near-inextensible
    bend_compliance: float = 1e-4
    air_damping: float = 0.02  # fraction of velocity lost per second

    @staticmethod
    def stiff() -> ClothSettings:
        """Stiff penalty and one big step: a naive explicit integrator diverges at once here."""
        return ClothSettings(penalty_stiffness=5e4, substeps=1, iterations=10)

    @property
    def particle_mass(self) -> float:
        return self.mass / self.resolution**2

    @property
    def explicit_stability_number(self) -> float:
        """omega * dt of the penalty spring per substep: an explicit step is unstable above 2."""
        step = self.frame_time / self.substeps
        return float(np.sqrt(self.penalty_stiffness / self.particle_mass) * step)


@dataclass(frozen=True)
class SphereMotion:
    """A sphere swinging along y through the cloth's plane (y = 0): centre (0, A sin(2 pi t / T), height)."""

    radius: float = 0.35
    amplitude: float = 0.8
    period: float = 4.0
    height: float = 1.2
    phase: float = 0.25  # start in front of the cloth (a quarter period in)

    def centre(self, t: float) -> np.ndarray:
        return np.array([0.0, self.amplitude * np.sin(2 * np.pi * (t / self.period + self.phase)), self.height])


@dataclass
class FrameReport:
    frame: int
    time: float
    kinetic_energy: float  # J
    potential_energy: float  # J, gravitational, relative to the start
    contacts: int  # particles within the thickness of the sphere
    penetration: float  # m, deepest particle inside the sphere's surface (0 if none)
    finite: bool


def cloth_grid(settings: ClothSettings) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions (n*n, 3) in the plane y = 0, hanging below z = size + 0.2, and faces (2(n-1)^2, 3)."""
    n = settings.resolution
    u = np.linspace(-settings.size / 2, settings.size / 2, n)
    x, z = np.meshgrid(u, settings.size + 0.2 - (u + settings.size / 2), indexing="xy")
    positions = np.stack([x, np.zeros_like(x), z], axis=-1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return positions, faces


def _constraint_groups(n: int) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """(first particle, second particle, is_bend) groups; no particle appears twice within a group."""
    idx = np.arange(n * n).reshape(n, n)
    groups = []

    def add(a, b, colour, bend):
        for value in (0, 1):
            keep = colour == value
            groups.append((a[keep].ravel(), b[keep].ravel(), bend))

    cols = np.arange(n)[None, :]
    rows = np.arange(n)[:, None]
    add(idx[:, :-1], idx[:, 1:], np.broadcast_to(cols[:, :-1] % 2, (n, n - 1)), False)  # horizontal
    add(idx[:-1, :], idx[1:, :], np.broadcast_to(rows[:-1, :] % 2, (n - 1, n)), False)  # vertical
    add(idx[:-1, :-1], idx[1:, 1:], np.broadcast_to(rows[:-1, :] % 2, (n - 1, n - 1)), False)  # diagonal
    add(idx[:-1, 1:], idx[1:, :-1], np.broadcast_to(rows[:-1, :] % 2, (n - 1, n - 1)), False)  # anti-diagonal
    add(idx[:, :-2], idx[:, 2:], np.broadcast_to((cols[:, :-2] // 2) % 2, (n, n - 2)), True)  # bend, rows
    add(idx[:-2, :], idx[2:, :], np.broadcast_to((rows[:-2, :] // 2) % 2, (n - 2, n)), True)  # bend, columns
    return groups


class Cloth:
    """XPBD cloth with penalty contact, implicit by default; positions and velocities are (n*n, 3) float64."""

    def __init__(self, settings: ClothSettings, *, contact: str = "implicit"):
        if contact not in ("implicit", "explicit"):
            raise ValueError(f"contact must be 'implicit' or 'explicit', got {contact!r}")
        self.settings = settings
        self.contact = contact
        self.rest, self.faces = cloth_grid(settings)
        self.positions = self.rest.copy()
        self.velocities = np.zeros_like(self.rest)
        n = settings.resolution
        self.pinned = np.array([0, n - 1])  # the two top corners
        self.inverse_mass = np.full(n * n, 1.0 / settings.particle_mass)
        self.inverse_mass[self.pinned] = 0.0
        self.groups = [(a, b, bend, np.linalg.norm(self.rest[a] - self.rest[b], axis=1))
                       for a, b, bend in _constraint_groups(n)]
        self.frame = 0
        self.time = 0.0
        self._start_height = self.rest[:, 2].copy()

    def step(self, query: DistanceQuery) -> FrameReport:
        """One frame: query the sphere's field at the predicted positions, then substeps of integration,
        contact (implicit penalty on the linearised distance) and constraint projection."""
        s = self.settings
        dt = s.frame_time / s.substeps
        predicted = self.positions + self.velocities * s.frame_time
        distance, normal = query(predicted.astype(np.float32))
        distance = distance.astype(np.float64)
        normal = normal.astype(np.float64)
        free = self.inverse_mass > 0
        mass = s.particle_mass
        for _ in range(s.substeps):
            self.velocities[free] += GRAVITY * dt
            self.velocities *= max(0.0, 1.0 - s.air_damping * dt)
            # contact: the distance at the current position, from the queried one and its gradient
            gap = distance + np.einsum("ij,ij->i", normal, self.positions - predicted)
            touching = free & (gap < s.thickness)
            if np.any(touching):
                v_n = np.einsum("ij,ij->i", self.velocities[touching], normal[touching])
                push = s.penalty_stiffness * (s.thickness - gap[touching])
                if self.contact == "implicit":
                    # implicit Euler of m dv = (k (thickness - gap) - c v) dt along the normal
                    new_v_n = (v_n + dt * push / mass) / (
                        1.0 + dt * dt * s.penalty_stiffness / mass + dt * s.penalty_damping / mass
                    )
                else:
                    new_v_n = v_n + dt * (push - s.penalty_damping * v_n) / mass
                self.velocities[touching] += (new_v_n - v_n)[:, None] * normal[touching]
            previous = self.positions.copy()
            self.positions = self.positions + self.velocities * dt
            self._project(dt)
            self.velocities = (self.positions - previous) / dt
        self.frame += 1
        self.time += s.frame_time
        return self.report(query)

    def _project(self, dt: float) -> None:
        s = self.settings
        multipliers = [np.zeros(len(a)) for a, _, _, _ in self.groups]
        for _ in range(s.iterations):
            for (a, b, bend, rest), lam in zip(self.groups, multipliers):
                alpha = (s.bend_compliance if bend else s.stretch_compliance) / (dt * dt)
                delta = self.positions[a] - self.positions[b]
                length = np.sqrt(np.einsum("ij,ij->i", delta, delta))
                direction = delta / np.maximum(length, 1e-12)[:, None]
                w = self.inverse_mass[a] + self.inverse_mass[b]
                step = (-(length - rest) - alpha * lam) / np.maximum(w + alpha, 1e-30)
                lam += step
                self.positions[a] += (self.inverse_mass[a] * step)[:, None] * direction
                self.positions[b] -= (self.inverse_mass[b] * step)[:, None] * direction

    def report(self, query: DistanceQuery | None = None, distance: np.ndarray | None = None) -> FrameReport:
        s = self.settings
        if distance is None and query is not None:
            distance = query(self.positions.astype(np.float32))[0]
        penetration = float(max(0.0, -np.min(distance))) if distance is not None and len(distance) else 0.0
        contacts = int(np.sum(distance < s.thickness)) if distance is not None else 0
        kinetic = 0.5 * s.particle_mass * float(np.sum(self.velocities**2))
        potential = s.particle_mass * 9.81 * float(np.sum(self.positions[:, 2] - self._start_height))
        finite = bool(np.all(np.isfinite(self.positions)) and np.all(np.isfinite(self.velocities)))
        return FrameReport(self.frame, self.time, kinetic, potential, contacts, penetration, finite)
