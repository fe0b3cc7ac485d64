"""Recordings in and out: bags as people record them. Topic discovery (:mod:`.topics`), message
classes and CDR (:mod:`.messages`), image decoding and encoding (:mod:`.images`: every
sensor_msgs/Image encoding a camera driver publishes and image_transport's compressed images),
camera_info as a calibration with its rectification (:mod:`.camera`), stereo pairing by stamp
(:mod:`.sync`), reading bags (:mod:`.bags`), reading them ahead in worker processes
(:mod:`.readahead`), repairing damaged ones (:mod:`.repair`) and writing them (:mod:`.writing`).
Knows nothing of the pipeline; needs no ROS runtime."""
