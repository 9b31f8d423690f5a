"""The command line (``cmion-mesh``)."""
