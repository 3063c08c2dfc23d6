"""Every name a user chooses from, every default that is one of them, and the numeric defaults that
both the library and the command line show, in one place: the command line reads its ``choices=``
and defaults here, the library its checks. Imports nothing (``vrnet --help`` answers without torch).

Abbreviations of the ModelNet40 protocol (the paper's Tables): settings CO (complete clouds), PV
(partial views), RS (randomly sampled source and target), PV+RS (both); splits UPC (unseen point
clouds: the test shapes of the training categories), UC (unseen categories: trained on the first
20, tested on the other 20), ND (noisy data: Gaussian noise on the UPC split).
"""

BACKENDS = ("ext", "torch")  # the compiled kernels, or their pure-PyTorch references
DEFAULT_BACKEND = "ext"
AUTO_DEVICE = "auto"  # a device option's: CUDA when there is one, else the CPU (train, eval)
TRANSFORMER_PRECISIONS = ("auto", "bf16", "fp32")  # auto: bfloat16 where the CPU multiplies it natively
PROCRUSTES_POINTS = ("rcp", "vcp")  # what the final Procrustes aligns the source with: RCPs (VRNet) or VCPs

SETTINGS = ("CO", "PV", "RS", "PV+RS")  # the paper's
MIXED = "mixed"  # training only: one of SETTINGS per pair
DEFAULT_SETTING = "PV"
SPLITS = ("UPC", "UC", "ND")
DEFAULT_SPLIT = "UPC"
# How a pair's rotation is drawn (vrnet_ext.data.protocol.random_motion): "protocol", the paper's,
# each Euler angle in [0, max_angle]; "symmetric", each in [-max_angle, max_angle]; "so3", uniform
# over all rotations (max_angle unused); "cube_residual", a uniform rotation turned back by the cube
# rotation nearest it: what is left from the rotation search's nearest start (at most 62.8 degrees).
ROTATION_RANGES = ("protocol", "symmetric", "so3", "cube_residual")
DEFAULT_ROTATION_RANGE = "protocol"
DEFAULT_MAX_ANGLE = 45.0  # the protocol's largest Euler angle, in degrees
# The ICP of the rotation search's multi-start ICP (vrnet_ext.geometry.alignment.ICPS): robust (Cauchy
# weights at the median residual) or trimmed (the nearer half of the nearest-point pairs).
SEARCH_ICPS = ("robust", "trimmed")
DEFAULT_SEARCH_ICP = "robust"
MAX_SEARCH_ICP_SLIDES = 64  # the most translations per rotation of that multi-start ICP (geometry.alignment.slides)
SEARCH_ICP_SLIDE_REACH = 1.5  # they span +- this many standard deviations of the target along its longest axis
ANY_ROTATION = 180.0  # VRNetConfig.max_rotation's default (degrees): the motion may turn the source by any angle
MAX_TURN_PENALTY = 10.0  # the largest VRNetConfig.rotation_search_turn_penalty (geometry.alignment.TurnPrior)

DEFAULT_MODEL = "vrnet-pv-upc-rcp"  # the shipped ModelNet40 model of the paper's main cell
DEFAULT_SCENE_MODEL = "scene-fpfh-vrnet-real"  # the shipped scene model (vrnet register --method vrnet)

GLOBAL_ESTIMATORS = ("auto", "sc2", "fpfh", "vrnet", "fgr", "icp")  # vrnet_ext.registration.global_estimators
# "auto": the first of these, checked by the second's estimate; when its refinement is doubtful or the
# check lands elsewhere, the others too, and the best fit that another confirms wins, else the scene
# model's (benchmarks/bench_default.py).
AUTO_MEMBERS = ("sc2", "fpfh", "vrnet")
DEFAULT_METHOD = "auto"
ICP_STEPS = ("point_to_point", "point_to_plane", "gicp")  # vrnet_ext.registration.icp_steps
DEFAULT_ICP_STEP = "point_to_plane"

SUCCESS_ROTATION_DEG = 15.0  # a registration counts as correct below this rotation error (3DMatch's) ...
SUCCESS_TRANSLATION = 0.3  # ... and below this translation error (the scans' unit; 0.3 m is 3DMatch's)

# register_scene: every pair of at most this many scans; for more, each scan with its next
# SCENE_NEIGHBOURS and with up to SCENE_LOOP_CANDIDATES scans the first poses put nearest.
SCENE_ALL_PAIRS_UP_TO = 30
SCENE_NEIGHBOURS = 2
SCENE_LOOP_CANDIDATES = 4
