"""`python -m perch_warp bench`: the reference speed workload, a ray-casting microbenchmark and its CPU peer.

Reference workload (fixed, so figures from different commits and devices compare):
the real YCB-Video frame ycbv test scene 2 image 1, the potted meat can (obj 9), the
visible table clipped to 1 m x 1 m (`perch_warp eval`'s region: nothing derived from
the ground truth), x/y step 1 cm, yaw step 0.1 rad over the full circle; height,
roll and pitch from the ground truth as in `perch_warp eval`. `--warmup` untimed runs
(default one, reported apart), then `--repeat` timed runs.

Microbenchmark: one ray per pixel of the whole (search-scale) image through the
engine's own `wp.Mesh`, for a few poses of the search grid that the image sees fully
(kernels.py), writing only the hit parameter. Peer: Open3D's
`RaycastingScene` (Embree, CPU) casting the same rays at the same mesh; both must
agree on hit/miss for at least 99.9 % of the rays.

Writes OUT/bench.json and OUT/bench.txt (the table, also printed).
"""

# The public names tools/ and tests use, from the modules that define them.
from .command import STAGES, add_arguments, format_report, run, time_search
from .environment import ENV_COMMIT, command_line, device_name, device_peak_mib, git_commit, git_dirty, host_peak_mib
from .kernels import MISS
from .raycast import (
    AGREEMENT_MIN,
    PEER_NAME,
    PEER_NOT_INSTALLED,
    compare_hits,
    open3d_raycast,
    peer_unavailable_reason,
    time_raycast,
    warp_raycast,
)
from .workload import (
    Workload,
    add_frame_arguments,
    add_pose_sample_arguments,
    default_dataset,
    load_workload,
    poses_in_view,
    sample_grid_poses,
    search_camera,
)

__all__ = [
    "AGREEMENT_MIN",
    "ENV_COMMIT",
    "MISS",
    "PEER_NAME",
    "PEER_NOT_INSTALLED",
    "STAGES",
    "Workload",
    "add_arguments",
    "add_frame_arguments",
    "add_pose_sample_arguments",
    "command_line",
    "compare_hits",
    "default_dataset",
    "device_name",
    "device_peak_mib",
    "format_report",
    "git_commit",
    "git_dirty",
    "host_peak_mib",
    "load_workload",
    "open3d_raycast",
    "peer_unavailable_reason",
    "poses_in_view",
    "run",
    "sample_grid_poses",
    "search_camera",
    "time_raycast",
    "time_search",
    "warp_raycast",
]
