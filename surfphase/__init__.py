"""SurfPhase: 3D bubble interfaces and metric velocities from synchronized high-speed videos."""

__version__ = "0.1.0"
