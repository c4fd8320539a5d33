"""dynqos: offload a drone's time-critical work to the edge and keep its real-time constraints.

The source folders `common/`, `onboard/`, `edge/` and `sim/` are mapped into this namespace by
setuptools (`package-dir` in pyproject.toml), so imports read `from dynqos.common.messages import State`.
"""

from dynqos._version import __version__

__all__ = ["__version__"]
