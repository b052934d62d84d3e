"""USB discovery through pyusb, against a fake libusb backend that behaves like the real one
(descriptors, string descriptors over control transfers, EACCES on open)."""

from __future__ import annotations

import errno
from types import SimpleNamespace

import pytest
import usb.backend
import usb.core

from twinfocus.errors import TwinFocusError
from twinfocus.sensors import usb_devices
from twinfocus.sensors.usb_devices import list_devices


class FakeBackend(usb.backend.IBackend):
    """Devices: (vid, pid, serial, product, denied)."""

    def __init__(self, devices):
        self.devices = devices
        self.opened = []

    def enumerate_devices(self):
        yield from range(len(self.devices))

    def get_device_descriptor(self, dev):
        vid, pid, serial, product, _ = self.devices[dev]
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=vid,
            idProduct=pid,
            bcdDevice=0x0100,
            iManufacturer=0,
            iProduct=2 if product else 0,
            iSerialNumber=3 if serial else 0,
            bNumConfigurations=1,
            address=10 + dev,
            bus=1,
            port_number=dev + 1,
            port_numbers=(dev + 1,),
            speed=3,
        )

    def open_device(self, dev):
        if self.devices[dev][4]:
            raise usb.core.USBError("Access denied (insufficient permissions)", errno=errno.EACCES)
        self.opened.append(dev)
        return dev

    def close_device(self, handle):
        self.opened.remove(handle)

    def ctrl_transfer(self, handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        assert bRequest == 0x06 and wValue >> 8 == 3  # GET_DESCRIPTOR, string
        index = wValue & 0xFF
        if index == 0:
            payload = bytes([4, 3, 0x09, 0x04])  # LANGID en-US
        else:
            text = {2: self.devices[handle][3], 3: self.devices[handle][2]}[index]
            body = text.encode("utf-16-le")
            payload = bytes([2 + len(body), 3]) + body
        data[: len(payload)] = type(data)(data.typecode, payload)
        return len(payload)


DEVICES = [
    (0x0451, 0xBEF3, "R0010234", "XDS110 (03.00.00.18) Embed with CMSIS-DAP", False),
    (0x2B03, 0xF880, None, None, True),  # ZED 2i, no permission
    (0x046D, 0xC077, None, "USB Optical Mouse", False),  # not ours
]


def test_lists_recognised_devices_with_serial_and_permission_hint():
    backend = FakeBackend(DEVICES)
    found = list_devices(backend)
    assert [(d.vendor_id, d.product_id) for d in found] == [(0x2B03, 0xF880), (0x0451, 0xBEF3)]
    zed, xds = found
    assert (xds.kind, xds.serial, xds.access) == ("radar", "R0010234", "ok")
    assert xds.product.startswith("XDS110")
    assert zed.kind == "camera" and zed.access == "permission denied" and zed.serial is None
    assert "udev rule" in zed.describe() and 'ATTRS{idVendor}=="2b03"' in zed.describe()
    assert backend.opened == []  # every handle that was opened was released
    everything = list_devices(backend, include_unknown=True)
    assert len(everything) == 3 and everything[-1].kind == "unknown" and everything[-1].name == "USB Optical Mouse"


def test_missing_libusb_is_a_clear_error(monkeypatch, capsys):
    import usb.backend.libusb0
    import usb.backend.libusb1

    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    monkeypatch.setattr(usb.backend.libusb0, "get_backend", lambda *a, **k: None)
    with pytest.raises(TwinFocusError, match="libusb is not installed.*apt-get install libusb-1.0-0"):
        list_devices()
    from twinfocus.cli import main

    assert main(["devices"]) == 2
    assert "libusb is not installed" in capsys.readouterr().err


def test_devices_command_prints_lines_and_json(monkeypatch, capsys):
    import json

    from twinfocus.cli import main

    monkeypatch.setattr(usb_devices, "default_backend", lambda: FakeBackend(DEVICES))
    assert main(["devices"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and out[0].startswith("camera") and "[2b03:f880]" in out[0] and "serial R0010234" in out[1]
    assert main(["devices", "--all", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["kind"] for r in rows] == ["camera", "radar", "unknown"]
    monkeypatch.setattr(usb_devices, "default_backend", lambda: FakeBackend(DEVICES[2:]))
    assert main(["devices"]) == 0
    assert "no recognised radar" in capsys.readouterr().out
