"""Entry point of a calibration worker process: ``python -m calibration.worker FD``.

Started by :class:`calibration.pool.ProcessTransport`; FD is its end of a socket pair.
"""
import sys

from calibration.pool import serve_socket

serve_socket(int(sys.argv[1]))
