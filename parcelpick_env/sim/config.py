"""Physics settings of the pybullet world, with their defaults in one place."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SimConfig:
    """Integrator and settling settings.

    Settling stops when no watched body's net motion over ``rest_window`` exceeds the velocity tolerances
    times the window (``Simulator.still``), or after ``max_settle_steps``.
    """

    timestep: float = 1.0 / 240.0
    solver_iterations: int = 50
    gravity: float = 9.8
    linear_velocity_tol: float = 0.01  # m/s
    angular_velocity_tol: float = 0.1  # rad/s
    max_settle_steps: int = 2400
    # s: a pile is at rest when no body's net motion over this window exceeds the velocity tolerances times it
    # (the pile builder's test: solver jitter that goes nowhere does not count, sliding does); the lift waits
    # this long after the held parcel has left the pile before the pile may sleep
    rest_window: float = 1.0 / 6.0
    collision_margin: float = 0.001  # m, kept small so parcels rest on their true surface
    max_hull_vertices: int = 64  # collision hulls are reduced to this many vertices for speed
    # Simulator.asleep: bodies slower than these may sleep (5x the rest tolerances: the jitter of the carry's
    # 60 Hz step, measured at up to 0.017 m/s and 0.22 rad/s in a resting pile; sleep zeroes the velocity)
    sleep_linear_velocity: float = 0.05  # m/s
    sleep_angular_velocity: float = 0.5  # rad/s
    # Bullet's motion measure (v^2 + w^2, SI units) below which a sleeper woken by a contact falls asleep
    # again after 2 s: 1 mm/s, still by any measure of the cell's
    sleep_motion: float = 1e-6
    # Load pybullet's EGL renderer plugin (OpenGL rendering for the camera) when the client starts:
    # shapes created before the plugin is loaded are invisible to it, so it cannot be added later.
    egl_rendering: bool = True

    def __post_init__(self) -> None:
        positive = {
            "timestep": self.timestep, "gravity": self.gravity,
            "linear_velocity_tol": self.linear_velocity_tol, "angular_velocity_tol": self.angular_velocity_tol,
            "sleep_motion": self.sleep_motion, "sleep_linear_velocity": self.sleep_linear_velocity,
            "sleep_angular_velocity": self.sleep_angular_velocity, "rest_window": self.rest_window,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"SimConfig.{name} must be > 0, got {value!r}")
        if self.timestep > 0.05:
            raise ValueError(f"SimConfig.timestep {self.timestep} s is too coarse (max 0.05 s)")
        for name in ("solver_iterations", "max_settle_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SimConfig.{name} must be >= 1, got {getattr(self, name)!r}")
        if not 0 <= self.collision_margin < 0.05:
            raise ValueError(f"SimConfig.collision_margin must be in [0, 0.05), got {self.collision_margin}")
        if self.max_hull_vertices < 8:
            raise ValueError(f"SimConfig.max_hull_vertices must be >= 8, got {self.max_hull_vertices}")
