"""ROS 2: the node (:mod:`.node`, started by :mod:`.node_main`), the pipeline's results as
messages (:mod:`.conversions`, :mod:`.outputs`), the Fast DDS profile for camera-sized
messages (:mod:`.transport`), and bags in the live graph and the node's outputs in bags
(:mod:`.bagtools`: play, record, process). Above the method, the recordings layer and the
survey; nothing below imports it."""
