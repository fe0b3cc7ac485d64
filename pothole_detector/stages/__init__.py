"""The pipeline's stages, one module each; none of them knows about ROS."""

import numba

# the node, the survey's threads and Ray actors may call the CPU kernels (Numba's, in
# census_cpu, slic_cpu, box_cpu, threshold, photometric, refine, components, perspective and
# rectify) from several threads
numba.config.THREADING_LAYER = "threadsafe"
