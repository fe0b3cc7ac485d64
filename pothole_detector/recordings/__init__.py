"""Recordings in: bags as people record them. Topic discovery (:mod:`.topics`), image decoding
(:mod:`.images`: every sensor_msgs/Image encoding a camera driver publishes and
image_transport's compressed images), camera_info as a calibration with its rectification
(:mod:`.camera`), reading bags (:mod:`.bags`) and reading them ahead in worker processes
(:mod:`.readahead`). Knows nothing of the pipeline; needs no ROS runtime."""
