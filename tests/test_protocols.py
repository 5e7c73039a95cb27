"""What both ends of a link share (`feedbench.protocols`): one address parser."""

import pytest

from feedbench.config import ConfigError
from feedbench.protocols.address import split_address


@pytest.mark.parametrize("address, expected", [
    ("10.0.0.2:5020", ("10.0.0.2", 5020)), ("localhost:0", ("localhost", 0)),
])
def test_a_host_reaches_host_and_port(address, expected):
    assert split_address(address, "bench.modbus") == expected


@pytest.mark.parametrize("address", ["", "10.0.0.2", ":5020", "10.0.0.2:x", "10.0.0.2:"])
def test_a_host_needs_both_and_the_error_names_the_field(address):
    with pytest.raises(ConfigError, match=rf"^bench\.modbus: expected host:port, got '{address}'$"):
        split_address(address, "bench.modbus")


@pytest.mark.parametrize("address, expected", [
    ("", ("127.0.0.1", 0)), ("0.0.0.0", ("0.0.0.0", 0)), (":29536", ("127.0.0.1", 29536)),
    ("127.0.0.1:5021", ("127.0.0.1", 5021)),
])
def test_a_listener_defaults_to_loopback_and_any_free_port(address, expected):
    assert split_address(address, "bench.socketcand", listen=True) == expected


def test_a_listener_refuses_a_port_that_is_no_number():
    with pytest.raises(ConfigError, match=r"^bench\.socketcand: expected host:port"):
        split_address("127.0.0.1:http", "bench.socketcand", listen=True)
