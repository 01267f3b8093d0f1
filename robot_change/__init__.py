"""robot_change: notice when the room in front of a robot is no longer the room it remembers.

depth -> point cloud -> voxel grid -> outlier removal -> plane removal -> Gaussian mixture
(split-EM stopped by MDL) -> greedy Earth Mover's Distance against the station's reference.
"""

from robot_change.errors import ConfigError, InputError, ProtocolError, RobotChangeError

__version__ = "0.1.0"

__all__ = ["ConfigError", "InputError", "ProtocolError", "RobotChangeError", "__version__"]
