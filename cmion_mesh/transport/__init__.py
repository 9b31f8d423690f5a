"""How embodiments reach each other: the transport interface, its zenoh adapter, an in-memory double, TLS."""
