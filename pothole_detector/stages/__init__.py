"""The pipeline's stages, one module each; none of them knows about ROS."""
