"""The cameras Aravis can list without broadcasting: USB3 Vision (and Aravis' "Fake" interface where enabled).

GigE Vision cameras are never listed here: Aravis' GigE discovery broadcasts on every interface of the host, so it
stays disabled (:func:`mocapd.io.aravis_camera.aravis_without_gige_discovery`); :mod:`mocapd.io.gige_discovery`
lists them on one named interface.
"""

from __future__ import annotations

from dataclasses import dataclass

from mocapd.io.aravis_camera import aravis_without_gige_discovery


@dataclass(frozen=True, slots=True)
class AravisDevice:
    """One device as Aravis lists it."""

    protocol: str
    """``USB3Vision`` or ``Fake``."""
    device_id: str
    """What ``device_id`` in ``[[cameras]]`` (and ``arv-tool-0.8 -n``) opens it by."""
    vendor: str
    model: str
    serial: str
    physical_id: str
    """Where it is attached (USB bus and port for USB3 Vision)."""


def list_aravis_devices() -> list[AravisDevice]:
    """Every device Aravis finds with GigE Vision disabled (blocking; enumerates the USB bus).

    Raises
    ------
    DeviceError
        If Aravis is not available.
    """
    aravis = aravis_without_gige_discovery()
    aravis.update_device_list()
    out = []
    for i in range(aravis.get_n_devices()):
        out.append(
            AravisDevice(
                protocol=str(aravis.get_device_protocol(i) or ""),
                device_id=str(aravis.get_device_id(i) or ""),
                vendor=str(aravis.get_device_vendor(i) or ""),
                model=str(aravis.get_device_model(i) or ""),
                serial=str(aravis.get_device_serial_nbr(i) or ""),
                physical_id=str(aravis.get_device_physical_id(i) or ""),
            )
        )
    return out
