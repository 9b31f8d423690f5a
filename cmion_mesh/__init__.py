"""cmion-mesh: CMION's mind-body middleware rebuilt as a zenoh peer-to-peer embodiment mesh."""

__version__ = "0.1.0"
