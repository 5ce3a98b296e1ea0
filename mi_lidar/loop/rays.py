"""The rays of a log for the loop: the core builder :class:`mi_lidar.log_rays.LogRays`."""

from ..log_rays import LogRays

__all__ = ["LogRays"]
