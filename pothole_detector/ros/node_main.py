"""The node's console script, ``pothole_detector_node``: Ctrl-C and SIGTERM end it quietly (exit
status 0, no traceback) from its first instant, also while ROS, the GPU libraries and the
node's modules load, before the node's own handlers take over."""

from __future__ import annotations

import os
import signal
import sys
from typing import Any, Sequence


def _leave(signum: int, frame: Any) -> None:
    os._exit(0)


def main(argv: Sequence[str] | None = None) -> int:
    """Set the quiet handlers, then load and run the node (node.main)."""
    signal.signal(signal.SIGINT, _leave)
    signal.signal(signal.SIGTERM, _leave)
    # imported here, after the handlers: loading rclpy and CuPy takes seconds
    from .node import main as run_node
    return run_node(argv)


if __name__ == "__main__":
    sys.exit(main())
