"""Endpoint URLs: every syntax users write maps to the pymavlink device string (and baud)."""

import pytest

from fisc_agent.mavlink.endpoints import EndpointError, parse_endpoint


@pytest.mark.parametrize("url, device, baud", [
    ("udpin:0.0.0.0:14540", "udpin:0.0.0.0:14540", None),
    ("udp:0.0.0.0:14550", "udpin:0.0.0.0:14550", None),          # pymavlink's udp: listens
    ("udpout:192.168.1.5:14550", "udpout:192.168.1.5:14550", None),
    ("udpbcast:192.168.1.255:14550", "udpbcast:192.168.1.255:14550", None),
    ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760", None),
    ("tcpin:0.0.0.0:5760", "tcpin:0.0.0.0:5760", None),
    ("udp://:14540", "udpin:0.0.0.0:14540", None),                 # MAVSDK listen, empty host
    ("udp://0.0.0.0:14540", "udpin:0.0.0.0:14540", None),
    ("udpin://0.0.0.0:14540", "udpin:0.0.0.0:14540", None),
    ("udpout://10.0.0.2:14580", "udpout:10.0.0.2:14580", None),
    ("tcp://10.0.0.2:5760", "tcp:10.0.0.2:5760", None),
    ("tcpout://10.0.0.2:5760", "tcp:10.0.0.2:5760", None),
    ("serial:///dev/ttyUSB0:921600", "/dev/ttyUSB0", 921600),
    ("serial:///dev/ttyUSB0", "/dev/ttyUSB0", 57600),
    ("/dev/ttyACM0:57600", "/dev/ttyACM0", 57600),
    ("/dev/ttyACM0,115200", "/dev/ttyACM0", 115200),             # MAVProxy --master style
    ("/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00:921600", "/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00", 921600),
    ("/dev/ttyTHS1", "/dev/ttyTHS1", 57600),
    ("COM3:57600", "COM3", 57600),
    ("serial://COM4:115200", "COM4", 115200),
])
def test_parse_endpoint_to_pymavlink_device(url, device, baud):
    ep = parse_endpoint(url)
    assert ep.device == device
    assert ep.baud == baud


def test_listening_and_kind():
    assert parse_endpoint("udp://:14540").listening
    assert not parse_endpoint("udpout:1.2.3.4:1").listening
    assert parse_endpoint("/dev/ttyACM0").kind == "serial"
    assert str(parse_endpoint("/dev/ttyACM0:57600")) == "/dev/ttyACM0@57600"


@pytest.mark.parametrize("url, words", [
    ("", "empty"),
    ("udpin:0.0.0.0", "HOST:PORT"),
    ("udpin:0.0.0.0:99999", "port"),
    ("udpout::14550", "host is required"),
    ("tcp://:5760", "host is required"),
    ("http://example.com:80", "unknown scheme"),
    ("14540", "not understood"),
    ("udpin:0.0.0.0:abc", "port"),
])
def test_bad_endpoints_name_the_problem(url, words):
    with pytest.raises(EndpointError) as exc:
        parse_endpoint(url)
    assert words in str(exc.value)
    assert repr(url) in str(exc.value)


@pytest.mark.parametrize("url, mavsdk", [
    ("udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
    ("udp://:14540", "udpin://0.0.0.0:14540"),
    ("udpout:10.0.0.2:14550", "udpout://10.0.0.2:14550"),
    ("tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
    ("/dev/ttyACM0:57600", "serial:///dev/ttyACM0:57600"),
])
def test_mavsdk_connection_urls(url, mavsdk):
    from fisc_agent.mavlink.mavsdk_backend import mavsdk_url

    assert mavsdk_url(parse_endpoint(url)) == mavsdk
