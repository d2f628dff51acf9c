"""The phalanx error tree: every error phalanx raises on purpose is a `PhalanxError`."""


class PhalanxError(Exception):
    """Base of every error phalanx raises on purpose."""


class ConfigError(PhalanxError):
    """A configuration file or value is wrong; the message names the file and field."""


class DriverError(PhalanxError):
    """A robot driver failed to connect, send or read."""


class DriverTimeout(DriverError):
    """A driver did not hear from the robot within its deadline."""


class DriverUnavailable(DriverError):
    """A driver's hardware library or device is missing."""


class ProtocolError(DriverError):
    """A robot sent bytes that do not follow its protocol."""


class TransportError(PhalanxError):
    """The Zenoh fabric could not be opened or used."""


class DeploymentError(PhalanxError):
    """A fleet could not be deployed: a host is missing or disagrees on the deployment."""


class RequestRefused(DeploymentError):
    """A host daemon refused a request; the message says which rule it broke."""
