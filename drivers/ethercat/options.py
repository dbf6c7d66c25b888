"""The ``ethercat`` driver's options and their checks against the joints and devices the
configuration gives the driver: everything ``check`` says before a bus is opened."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from aiohal.fieldbus.pdo_options import DriveUnitOptions, parse_pdo_entry, pdo_issues
from aiohal.fieldbus.pdo_options import parse_number as _number
from aiohal.hal import FiniteFloat, Options

from .sm_watchdog import max_ms

IMU_VARIABLES = {
    "quaternion": "Orientation",
    "angular_velocity": "Angular velocity",
    "linear_acceleration": "Linear acceleration",
    "status": "Status",
}
FT_VARIABLES = {"wrench": "Wrench", "status": "Status"}
FT_CONTROL = "Control"  # the F/T output that tares, used when the slave maps one (variables.control)


#: the SM watchdog's default: 50 bus cycles at 1 kHz, above what the keep-alive needs
#: (1.5 x keepalive_after_ms + 2 = 32 ms at its default)
SM_WATCHDOG_MS = 50.0

RX_PDOS, TX_PDOS = (0x1600, 0x17FF), (0x1A00, 0x1BFF)  # where CiA 301 puts the PDO mapping objects


class SlaveOptions(Options):
    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_ -]*$", description="Bus variables are '<name>.<variable>'.")
    kind: Literal["cia402", "imu", "force_torque", "other"] = "other"
    joint: str | None = Field(None, description="cia402: the joint this drive moves.")
    device: str | None = Field(None, description="imu / force_torque: the robot device it fills.")
    vendor_id: int | None = Field(None, ge=0, description="Checked at bring-up when given.")
    product_code: int | None = Field(None, ge=0, description="Checked at bring-up when given.")
    counts_per_rev: FiniteFloat | None = Field(None, gt=0)
    gear_ratio: FiniteFloat | None = Field(None, gt=0)
    rated_torque: FiniteFloat | None = Field(None, gt=0)
    position_offset: FiniteFloat = Field(0.0, description="rad added to the drive's position.")
    names: dict[str, str | list[str]] = Field(default_factory=dict, description="Bus variable names by address.")
    variables: dict[str, str] = Field(default_factory=dict, description="imu / force_torque: which variables to read.")
    sync0: bool | None = Field(
        None, description="SYNC0 on this slave (default: options.sync0 for a cia402 drive, off for others)."
    )
    rx_pdos: dict[str, list[str]] | None = Field(
        None,
        description="Remap the outputs: the RxPDOs assigned (0x1C12), in order, each with its entries "
        "'index:subindex:bits' (e.g. '0x607A:0:32'; an empty list assigns the PDO as the slave "
        "maps it). Written over CoE in PREOP, before the mapping is read.",
    )
    tx_pdos: dict[str, list[str]] | None = Field(None, description="Remap the inputs: the TxPDOs (0x1C13), as rx_pdos.")

    def pdo_assignments(self) -> list[tuple[int, list[tuple[int, list[int]]]]]:
        """(0x1C12 or 0x1C13, [(PDO, mapping entries)]) to write; checked by check_config."""
        return [
            (assign, [(_number(pdo), [parse_pdo_entry(e) for e in entries]) for pdo, entries in pdos.items()])
            for assign, pdos in ((0x1C12, self.rx_pdos), (0x1C13, self.tx_pdos))
            if pdos is not None
        ]


class EthercatOptions(Options):
    interface: str = Field(min_length=1, description="The one network interface the master opens.")
    slaves: list[SlaveOptions] = Field(min_length=1, description="Every slave, in bus order.")
    drive_defaults: DriveUnitOptions = Field(default_factory=DriveUnitOptions)
    exchange: Literal["split", "immediate"] = "split"
    receive_timeout_us: int = Field(200, ge=10, le=100_000, description="Wait for the cyclic frame in read().")
    bringup_receive_timeout_us: int = Field(50_000, ge=1000, le=1_000_000)
    frame_timeout_us: int | None = Field(
        None, ge=500, le=100_000, description="pysoem.settings.timeouts.ret (process-wide) for bring-up frames."
    )
    take_over: bool = Field(
        False,
        description="Bring up a bus whose slaves are in OP under another master (not "
        "aiohal), knocking that one off; refused otherwise.",
    )
    overlap_map: bool = Field(False, description="config_overlap_map (inputs and outputs share logical addresses).")
    dc: bool = Field(True, description="Distributed clocks: config_dc, and FRMW of the system time each cycle.")
    dc_static_frames: int = Field(
        3000,
        ge=0,
        le=1_000_000,
        description="Static drift compensation: frames carrying the reference clock's time to every "
        "slave, back to back after config_dc and before SYNC0 and SAFEOP (the simulated ESCs lock "
        "within 3000; the ETG recommends about 15000 for hardware).",
    )
    dc_lock: bool = Field(
        False,
        description="Keep the loop's deadlines locked to the reference clock, half a cycle before "
        "SYNC0 (a PI on the reference's time each cycle); needs dc.",
    )
    sync0: bool = Field(
        False,
        description="Activate SYNC0 at the loop's period on every cia402 drive (DC-synchronous "
        "drives need it, e.g. in CSP); needs dc.",
    )
    sync0_shift_us: FiniteFloat = Field(0.0, ge=0, description="SYNC0 pulses this long after the period's DC time.")
    wkc_error_limit: int = Field(
        10, ge=1, le=10_000, description="Bad cycles in a row before the slaves' states are read."
    )
    al_check_interval_ms: FiniteFloat = Field(
        20.0,
        ge=1,
        le=10_000,
        description="Every slave's AL state is read this often, off the tick: a slave in SAFEOP "
        "(+ERROR) keeps its working counter, so only its state tells.",
    )
    recover_interval_s: FiniteFloat = Field(1.0, gt=0, description="Between two recovery steps of a lost sensor.")
    bringup_attempts: int = Field(2, ge=1, le=10, description="A bring-up that fails is tried again from scratch.")
    enable_on_open: bool = Field(True, description="Enable the drives at bring-up; else enable_drives() does.")
    keepalive_after_ms: FiniteFloat = Field(
        20.0, gt=0, le=1000, description="The driver cycles the bus itself when the loop has not for this long."
    )
    enable_timeout_s: FiniteFloat = Field(3.0, gt=0)
    safeop_timeout_s: FiniteFloat = Field(
        2.0, gt=0, description="Mapped slaves reach SAFEOP within this (a request lost in a stall is sent again)."
    )
    op_timeout_s: FiniteFloat = Field(
        10.0,
        gt=0,
        description="SAFEOP -> OP within this (a slave's ESI gives its SafeopOpTimeout; drives can take seconds).",
    )
    stuck_after_ms: FiniteFloat = Field(1000.0, gt=0, description="A drive making no progress this long is faulted.")
    sm_watchdog_ms: FiniteFloat = Field(
        SM_WATCHDOG_MS,
        ge=0,
        description="The process-data (SM) watchdog time written to every slave with outputs "
        "before OP and read back after it: when no frame reaches a slave for this long (the whole "
        "process frozen), it leaves OP and its drive goes to its safe state (0x6007) on its own. "
        "A slave that does not arm it fails the bring-up. 0: every slave keeps its own setting, "
        "unchecked (a warning). At most 6553.5 ms (0xFFFF units of 100 us).",
    )

    def sync0_slaves(self) -> list[int]:
        """Bus positions of the slaves whose SYNC0 is activated."""
        return [
            i
            for i, s in enumerate(self.slaves)
            if (s.sync0 if s.sync0 is not None else self.sync0 and s.kind == "cia402")
        ]


def option_issues(options: EthercatOptions, joints: list[str], devices: dict[str, str]) -> list[tuple[str, str]]:
    """What :meth:`EthercatDriver.check_config` finds: slaves against the joints and devices
    given to the driver, remapped PDOs, timings that cannot work together."""
    issues: list[tuple[str, str]] = []
    seen: dict[str, int] = {}
    drives_for: dict[str, int] = {}
    issues += _sm_watchdog_issues(options)
    for i, s in enumerate(options.slaves):
        where = f"options.slaves[{i}]"
        key = s.name.strip().lower().replace(" ", "_")
        if key in seen:
            issues.append((f"{where}.name", f"{s.name!r} is also the name of slaves[{seen[key]}]"))
        seen[key] = i
        if s.kind == "cia402":
            if s.joint is None:
                issues.append((f"{where}.joint", "a cia402 drive needs the joint it moves"))
            elif s.joint not in joints:
                issues.append((f"{where}.joint", f'"{s.joint}" is not one of this driver\'s joints {joints}'))
            elif s.joint in drives_for:
                issues.append((f"{where}.joint", f'"{s.joint}" is already moved by slaves[{drives_for[s.joint]}]'))
            else:
                drives_for[s.joint] = i
        elif s.joint is not None:
            issues.append((f"{where}.joint", f"only a cia402 drive moves a joint, this slave is {s.kind!r}"))
        if s.kind in ("imu", "force_torque"):
            if s.device is None:
                issues.append((f"{where}.device", f"an {s.kind} slave needs the device it fills"))
            elif devices.get(s.device) != s.kind:
                issues.append((f"{where}.device", f'"{s.device}" is not an {s.kind} device of this driver'))
            allowed = IMU_VARIABLES if s.kind == "imu" else {**FT_VARIABLES, "control": FT_CONTROL}
            for key in s.variables:
                if key not in allowed:
                    issues.append((f"{where}.variables.{key}", f"unknown; expected one of {sorted(allowed)}"))
        elif s.device is not None:
            issues.append((f"{where}.device", f"a {s.kind} slave fills no device"))
        for key, pdos, (low, high) in (("rx_pdos", s.rx_pdos, RX_PDOS), ("tx_pdos", s.tx_pdos, TX_PDOS)):
            issues += pdo_issues(f"{where}.{key}", pdos, low, high)
    if not options.dc and options.sync0_slaves():
        issues.append(("options.sync0", "SYNC0 needs distributed clocks (options.dc = true)"))
    if not options.dc and options.dc_lock:
        issues.append(("options.dc_lock", "locking the loop to the reference clock needs options.dc = true"))
    for joint in joints:
        if joint not in drives_for:
            issues.append(("joints", f'joint "{joint}" has no cia402 drive in options.slaves'))
    served = {s.device for s in options.slaves}
    for name in devices:
        if name not in served:
            issues.append(("devices", f'device "{name}" has no slave in options.slaves'))
    return issues


def _sm_watchdog_issues(options: EthercatOptions) -> list[tuple[str, str]]:
    """``sm_watchdog_ms`` must fit the registers at the ESC's default divider (bring-up checks
    each slave's own) and outlast the keep-alive's gaps."""
    ms = options.sm_watchdog_ms
    default = " (the default)" if "sm_watchdog_ms" not in options.model_fields_set else ""
    if ms == 0:
        return []
    if ms > max_ms():
        return [
            (
                "options.sm_watchdog_ms",
                f"{ms:g} ms does not fit the watchdog registers: at most {max_ms():g} ms "
                f"(0x0420 holds 0xFFFF units of 100 us at the ESC's default divider)",
            )
        ]
    # the keep-alive cycles the bus within 1.5 x keepalive_after_ms of the last tick
    least = 1.5 * options.keepalive_after_ms + 2
    if ms < least:
        return [
            (
                "options.sm_watchdog_ms",
                f"{ms:g} ms{default} would trip between runs: make it at least "
                f"1.5 x keepalive_after_ms + 2 ms ({least:g}), or lower keepalive_after_ms",
            )
        ]
    return []
