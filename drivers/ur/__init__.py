"""Universal Robots e-Series over RTDE (ur_rtde) and the dashboard server: ``ur://HOST[?model=ur5e]``."""

from station.drivers.ur.calibration import export_files, read_calibration_conf
from station.drivers.ur.dashboard import DashboardClient
from station.drivers.ur.robot import URRobot

__all__ = ["DashboardClient", "URRobot", "export_files", "read_calibration_conf"]
