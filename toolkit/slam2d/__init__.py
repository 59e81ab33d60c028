"""2D lidar SLAM in the manner of Cartographer: probability-grid submaps, scan-to-submap
matching (correlative search + continuous refinement), a sparse pose graph with
branch-and-bound loop closure. ``LidarSlam2D`` is the algorithm; ``run_slam`` feeds it a
recording; ``Slam2DStage`` is the recipe stage."""

from toolkit.slam2d.config import Slam2DConfig
from toolkit.slam2d.slam import LidarSlam2D, SlamResult

__all__ = ["LidarSlam2D", "Slam2DConfig", "SlamResult"]
