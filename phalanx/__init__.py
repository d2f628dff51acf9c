"""phalanx: tightly coupled formations of differential-drive robots, forwards and backwards."""

__version__ = "0.1.0"
