"""What the tests share: processes they start (probes, publishers, stand-ins), holders, minds and the browser."""
