"""Which radars, capture boards and cameras are plugged in (USB, through pyusb and libusb).

Devices are recognised by vendor and product id (:data:`KNOWN_DEVICES`). Reading a device's
serial number needs permission to open it; when that is refused the device is still listed, with
``access == "permission denied"`` and a hint (udev rule / group). A missing libusb raises
:class:`TwinFocusError` saying how to install it.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass

from twinfocus.errors import TwinFocusError

LIBUSB_MISSING = (
    "libusb is not installed (pyusb found no backend): install the system library, e.g. "
    "'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu), 'brew install libusb' (macOS), "
    "or on Windows put libusb-1.0.dll next to Python"
)
PERMISSION_HINT = (
    "no permission to open it: add a udev rule such as "
    'SUBSYSTEM=="usb", ATTRS{{idVendor}}=="{vid:04x}", MODE="0666" in /etc/udev/rules.d/ '
    "(then 'sudo udevadm control --reload-rules && sudo udevadm trigger'), or join the plugdev/dialout group"
)


@dataclass(frozen=True)
class KnownDevice:
    vendor_id: int
    product_id: int
    kind: str  # "radar" | "capture_board" | "camera" | "camera_sensors"
    name: str


#: (vendor id, product id) of the hardware TwinFocus works with. Generic bridge chips (XDS110,
#: CP2105, FT4232H) are named by what they sit on in this setup; other products use them too.
KNOWN_DEVICES: tuple[KnownDevice, ...] = (
    KnownDevice(
        0x0451,
        0xBEF3,
        "radar",
        "TI XDS110 probe of a single-chip mmWave EVM (xWR14xx/16xx/18xx/68xx BOOST): CLI + data UARTs",
    ),
    KnownDevice(
        0x10C4, 0xEA70, "radar", "Silicon Labs CP2105 of a TI mmWave EVM (xWR6843ISK/AOP, xWR1843AOP): CLI + data UARTs"
    ),
    KnownDevice(
        0x0403,
        0x6011,
        "capture_board",
        "FTDI FT4232H of a TI DCA1000EVM / MMWCAS-RF-EVM (radar SPI, I2C and UART control)",
    ),
    KnownDevice(0x2B03, 0xF880, "camera", "Stereolabs ZED 2i (UVC side-by-side stereo)"),
    KnownDevice(0x2B03, 0xF881, "camera_sensors", "Stereolabs ZED 2i sensors (IMU, barometer, magnetometer; HID)"),
    KnownDevice(0x2B03, 0xF780, "camera", "Stereolabs ZED 2 (UVC side-by-side stereo)"),
    KnownDevice(0x2B03, 0xF781, "camera_sensors", "Stereolabs ZED 2 sensors (HID)"),
    KnownDevice(0x2B03, 0xF682, "camera", "Stereolabs ZED Mini (UVC side-by-side stereo)"),
    KnownDevice(0x2B03, 0xF681, "camera_sensors", "Stereolabs ZED Mini sensors (HID)"),
    KnownDevice(0x2B03, 0xF582, "camera", "Stereolabs ZED (UVC side-by-side stereo)"),
)
_BY_ID = {(d.vendor_id, d.product_id): d for d in KNOWN_DEVICES}


@dataclass(frozen=True)
class UsbDevice:
    """One attached device as found on the bus.

    access : ``"ok"``, ``"permission denied"``, ``"no strings"`` (the device reports no string
    descriptors) or ``"error: ..."``; serial / product are None unless readable.
    """

    bus: int
    address: int
    vendor_id: int
    product_id: int
    kind: str
    name: str
    serial: str | None
    product: str | None
    access: str

    @property
    def known(self) -> bool:
        return self.kind != "unknown"

    def describe(self) -> str:
        """One line for people."""
        line = f"{self.kind:<14} {self.name} [{self.vendor_id:04x}:{self.product_id:04x}] bus {self.bus} address {self.address}"
        if self.serial:
            line += f" serial {self.serial}"
        if self.access == "permission denied":
            line += " -- " + PERMISSION_HINT.format(vid=self.vendor_id)
        elif self.access not in ("ok", "no strings"):
            line += f" -- {self.access}"
        return line


def default_backend():
    """The libusb backend pyusb would use; :class:`TwinFocusError` when libusb is absent."""
    try:
        import usb.backend.libusb0
        import usb.backend.libusb1
    except ImportError:
        raise TwinFocusError("pyusb is not installed: pip install pyusb") from None
    for module in (usb.backend.libusb1, usb.backend.libusb0):
        backend = module.get_backend()
        if backend is not None:
            return backend
    raise TwinFocusError(LIBUSB_MISSING)


def list_devices(backend=None, include_unknown: bool = False) -> list[UsbDevice]:
    """Attached USB devices, recognised ones first (all of them with ``include_unknown``).

    backend : a pyusb backend (default :func:`default_backend`).
    """
    import usb.core
    import usb.util

    backend = default_backend() if backend is None else backend
    try:
        found = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError:
        raise TwinFocusError(LIBUSB_MISSING) from None
    except usb.core.USBError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM):
            raise TwinFocusError(
                "no permission to list USB devices (run as a user allowed to read /dev/bus/usb)"
            ) from None
        raise TwinFocusError(f"listing USB devices failed: {exc}") from None
    out = []
    for dev in found:
        vid, pid = int(dev.idVendor), int(dev.idProduct)
        known = _BY_ID.get((vid, pid))
        if known is None and not include_unknown:
            continue
        serial = product = None
        access = "ok"
        try:
            langids = usb.util.get_langids(dev)
            if not langids:
                access = "no strings"
            else:
                serial = usb.util.get_string(dev, dev.iSerialNumber, langids[0]) if dev.iSerialNumber else None
                product = usb.util.get_string(dev, dev.iProduct, langids[0]) if dev.iProduct else None
        except usb.core.USBError as exc:
            access = "permission denied" if exc.errno in (errno.EACCES, errno.EPERM) else f"error: {exc}"
        except (ValueError, NotImplementedError) as exc:
            access = f"error: {exc}"
        finally:
            try:
                usb.util.dispose_resources(dev)
            except Exception:  # noqa: BLE001 - releasing a device that went away is not an error here
                pass
        out.append(
            UsbDevice(
                bus=int(getattr(dev, "bus", 0) or 0),
                address=int(getattr(dev, "address", 0) or 0),
                vendor_id=vid,
                product_id=pid,
                kind=known.kind if known else "unknown",
                name=known.name if known else (product or "unrecognised device"),
                serial=serial,
                product=product,
                access=access,
            )
        )
    out.sort(key=lambda d: (not d.known, d.kind, d.bus, d.address))
    return out
