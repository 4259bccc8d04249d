"""graftbench: frozen-backbone grafting as a pytest benchmark harness."""

import logging

# torchcodec is a LeRobot dependency that cannot load without system FFmpeg; LeRobot then falls
# back to pyav (and our suites store images, not video) but logs a 100-line traceback per call.
logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
