"""One exception tree for the whole package.

Every error the driver raises on purpose is a ``VfdError``; callers that must
never crash (ROS callbacks, the drive loop) catch ``VfdError`` and report it.
"""

#: characters of user input shown in an error message (a parameter name may be 10 kB)
QUOTE_LIMIT = 64


def quote(value: object) -> str:
    """Return user input fit for an error message, a reply or a log line: repr'd, capped."""
    shown = repr(value)
    if len(shown) <= QUOTE_LIMIT:
        return shown
    return f'{shown[:QUOTE_LIMIT]}... ({len(shown)} characters)'


class VfdError(Exception):
    """Base of all errors raised by vfd_ros2."""


class ProfileError(VfdError):
    """A drive profile file is missing, malformed or inconsistent."""


class ParameterError(VfdError):
    """A parameter request is invalid: unknown name, read-only, out of range."""


class TransportError(VfdError):
    """The link to the drive failed (no reply, malformed reply, port gone)."""


class CommTimeout(TransportError):
    """The drive did not answer within the transport timeout."""


class BadFrame(TransportError):
    """A reply arrived but was malformed (CRC, length, wrong unit id)."""


class PassingRefusal(TransportError):
    """The drive answered an exception that may pass (busy, a gateway's): a failed exchange."""


class ProtocolException(VfdError):
    """The drive answered with a protocol exception (e.g. a Modbus exception code).

    ``code`` is the number on the wire and ``text`` its meaning in the drive's
    own manual, which for some drives differs from the Modbus specification.
    """

    def __init__(self, code: int, text: str, request: str = '') -> None:
        self.code = code
        self.text = text
        self.request = request
        where = f' to {request}' if request else ''
        super().__init__(f'drive answered exception {code} ({text}){where}')


class TransportLoadError(VfdError):
    """A transport plugin name is unknown or its module cannot be imported."""
