"""Load the designed panel drive into an arbitrary-waveform generator over VISA (SCPI).

One cycle of commanded voltage per panel (:class:`Program`, from a
:class:`asynhdr.waveform.Design` or from the files :mod:`asynhdr.waveform_io` wrote) is
sent as two arbitrary waveforms, channel 1 the scene panel and channel 2 the reference
panel, each with its sample rate, amplitude and offset into a high-impedance load (an
LCD panel is a capacitor: a generator left at its 50-ohm default would put twice the
programmed voltage on it), both channels started together, and a Sync/trigger output
whose rising edge marks each cycle start (wire it to the event camera's trigger input).

Each instrument family speaks its own SCPI dialect, picked from its ``*IDN?`` answer
(:func:`detect_dialect`); every dialect is a record (:class:`Dialect`) in
:data:`DIALECTS`:

``keysight``  Keysight/Agilent 33500B and 33600A (``DATA:ARB:DAC``, ``FUNC:ARB``,
              ``FUNC:ARB:SRAT``, ``FUNC:ARB:SYNC``, ``MARK:POIN`` and ``OUTP:SYNC``);
              errors from ``SYST:ERR?``.
``rigol``     Rigol DG800, DG900, DG1000Z, DG2000 (``:TRACe:DATA:DAC16 VOLATILE,END``,
              ``:APPLy:ARBitrary <rate>,<amp>,<offset>``, ``:PHASe:SYNChronize``,
              ``:OUTPut:SYNC``); errors from ``:SYSTem:ERRor?``.
``siglent``   Siglent SDG1000X, SDG2000X, SDG6000X (``C1:WVDT``, ``C1:ARWV``,
              ``C1:SRATE MODE,TARB``, ``C1:BSWV``, ``C1:SYNC``, ``MODE PHASELOCKED``). These
              have no error queue: the upload is checked by reading the state back
              (``C1:ARWV?``, ``C1:SRATE?``, ``C1:BSWV?``, ``C1:OUTP?``).

Waveform data go as IEEE 488.2 definite-length blocks (``#<n><length><bytes>``) of
little-endian 16-bit codes where the dialect takes them (``transfer="binary"``, the
default; Siglent's ``WAVEDATA`` is raw little-endian int16 without a block header), or
as comma-separated decimal codes (``transfer="ascii"``: Keysight ``DATA:ARB:DAC`` and
Rigol DG1000Z/DG4000 ``:DATA:DAC``). After every command the error queue is read, so a
rejected command is named (:class:`GeneratorError`). The command lists and the manuals
they follow are in ``docs/generator.md``.

Library code: no printing; progress through ``progress(done, total)``.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from asynhdr.waveform_io import ChannelScale, WaveformFiles, channel_scale

__all__ = [
    "DIALECTS",
    "TRANSFERS",
    "Command",
    "Dialect",
    "GeneratorError",
    "Program",
    "UploadReport",
    "detect_dialect",
    "ieee_block",
    "scpi_commands",
    "upload",
]

logger = logging.getLogger(__name__)

TRANSFERS = ("binary", "ascii")
"""Waveform data transfer modes: IEEE 488.2 binary blocks, or decimal codes."""

DEFAULT_TIMEOUT_MS = 20_000
"""VISA timeout: a 10,000-point waveform over USB-TMC takes well under a second, but an
instrument writes it to memory before it answers the next query."""

_MAX_ERRORS = 32


class GeneratorError(RuntimeError):
    """The instrument refused or did not take a command, or answered unexpectedly."""


@dataclass(frozen=True, eq=False)
class Program:
    """What goes to the generator: one cycle per channel at one sample rate.

    Attributes
    ----------
    voltage_v : ``(channel 1, channel 2)``: scene panel and reference panel, volts.
    sample_rate_hz : samples per second (``period_us * sample_rate_hz / 1e6`` samples).
    period_us : cycle length, µs.
    carrier_hz : the drive's AC carrier (None: DC), for the record.
    names : waveform names in the instrument's volatile memory.
    sync_channel : the channel whose Sync output marks the cycle start.
    """

    voltage_v: tuple[np.ndarray, np.ndarray]
    sample_rate_hz: float
    period_us: int
    carrier_hz: float | None = None
    names: tuple[str, str] = ("ASYNHDR1", "ASYNHDR2")
    sync_channel: int = 1

    def __post_init__(self) -> None:
        v1, v2 = (np.asarray(v, dtype=np.float64) for v in self.voltage_v)
        if v1.shape != v2.shape or v1.ndim != 1 or v1.size < 8:
            raise ValueError(f"both channels need the same number of samples, at least 8 (the "
                             f"generators' minimum); got {v1.shape} and {v2.shape}")
        if not (math.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise ValueError(f"sample_rate_hz must be positive, got {self.sample_rate_hz!r}")
        expected = self.period_us * self.sample_rate_hz / 1e6
        if abs(expected - v1.size) > 1e-6 * max(1.0, expected):
            raise ValueError(f"{v1.size} samples at {self.sample_rate_hz:g} Sa/s do not make "
                             f"a {self.period_us} µs cycle ({expected:g} samples)")
        for name in self.names:
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,11}", name):
                raise ValueError(f"waveform name {name!r}: a letter then up to 11 letters, "
                                 "digits or '_' (the 33500B's limit, the shortest)")
        if self.sync_channel not in (1, 2):
            raise ValueError(f"sync_channel must be 1 or 2, got {self.sync_channel!r}")
        object.__setattr__(self, "voltage_v", (v1, v2))

    @classmethod
    def from_design(cls, design: Any, **kw: Any) -> Program:
        """From an :class:`asynhdr.waveform.Design`."""
        return cls(voltage_v=(design.samples(1), design.samples(2)),
                   sample_rate_hz=design.sample_rate_hz, period_us=design.period_us,
                   carrier_hz=design.carrier_hz, **kw)

    @classmethod
    def from_files(cls, files: WaveformFiles, **kw: Any) -> Program:
        """From waveform files read by :func:`asynhdr.waveform_io.read_waveform_files`."""
        return cls(voltage_v=files.voltage_v, sample_rate_hz=files.sample_rate_hz,
                   period_us=files.period_us, carrier_hz=files.carrier_hz, **kw)

    @property
    def n_samples(self) -> int:
        """Samples per cycle."""
        return int(self.voltage_v[0].size)

    @property
    def frequency_hz(self) -> float:
        """Repetition rate of one cycle, ``1e6 / period_us``."""
        return 1e6 / self.period_us

    def scale(self, channel: int) -> ChannelScale:
        """Amplitude, offset and normalised samples of channel 1 or 2."""
        return channel_scale(self.voltage_v[channel - 1])

    @property
    def marker_point(self) -> int:
        """Sample at which the Sync pulse falls (it rises at sample 1): the middle."""
        return self.n_samples // 2


@dataclass(frozen=True)
class Command:
    """One SCPI program message: ``text`` then, for binary transfers, ``payload`` bytes."""

    text: str
    payload: bytes | None = None
    payload_note: str = ""

    def wire(self) -> bytes:
        """The bytes sent, without the terminator."""
        return self.text.encode("ascii") + (self.payload or b"")

    def show(self, *, max_chars: int = 110) -> str:
        """A printable form: binary payloads summarised, long decimal lists cut."""
        if self.payload is not None:
            return f"{self.text}<{self.payload_note}>"
        if len(self.text) > max_chars:
            n_values = self.text.count(",")
            return f"{self.text[:max_chars]}... ({len(self.text):,} characters, " \
                   f"about {n_values:,} values)"
        return self.text


def ieee_block(data: bytes) -> bytes:
    """IEEE 488.2 definite-length arbitrary block: ``#``, the digit count of the length,
    the length in bytes, the bytes (IEEE 488.2-1992, 7.7.6.2)."""
    n = str(len(data))
    if len(n) > 9:
        raise ValueError(f"a definite-length block holds at most 999,999,999 bytes, got {n}")
    return b"#" + str(len(n)).encode("ascii") + n.encode("ascii") + data


# --------------------------------------------------------------------------- dialects

Check = Callable[[str], str | None]
"""Read-back check: the instrument's answer -> None if right, else what is wrong."""


@dataclass(frozen=True)
class Dialect:
    """One family's SCPI: how to recognise it, build the upload, and check it.

    Attributes
    ----------
    name, title : registry key and the family in words.
    idn : pattern matched against ``manufacturer,model`` of ``*IDN?`` (case-insensitive).
    transfers : the data transfers the family accepts.
    build : ``build(program, transfer) -> [Command]``.
    error_query : the error-queue query, or None when the family has none.
    no_error : pattern of the error query's answer when the queue is empty.
    verify : ``verify(program) -> [(query, check, command it checks)]`` read-backs.
    manual : the programming guide the commands follow.
    """

    name: str
    title: str
    idn: re.Pattern[str]
    transfers: tuple[str, ...]
    build: Callable[[Program, str], list[Command]]
    error_query: str | None
    no_error: re.Pattern[str] = re.compile(r"^\s*[+]?0\s*,")
    verify: Callable[[Program], list[tuple[str, Check, str]]] = field(
        default=lambda program: [])
    manual: str = ""

    def commands(self, program: Program, *, transfer: str = "binary") -> list[Command]:
        """The upload's command list (what ``--dry-run`` prints)."""
        if transfer not in TRANSFERS:
            raise ValueError(f"transfer must be one of {TRANSFERS}, got {transfer!r}")
        if transfer not in self.transfers:
            raise ValueError(f"{self.title} takes waveform data only as "
                             f"{' or '.join(self.transfers)}, not {transfer}")
        return self.build(program, transfer)


def _num(x: float) -> str:
    return f"{x:.10g}"


def _volts(x: float) -> str:
    return f"{x:.6f}"


def _i16_le(codes: np.ndarray) -> bytes:
    return np.asarray(codes, dtype="<i2").tobytes()


def _keysight(program: Program, transfer: str) -> list[Command]:
    cmds = [Command("*CLS")]
    if transfer == "binary":
        cmds.append(Command("FORM:BORD SWAP"))  # least significant byte first
    for k in (1, 2):
        sc, name = program.scale(k), program.names[k - 1]
        codes = sc.codes()
        cmds += [Command(f"OUTP{k} OFF"), Command(f"SOUR{k}:DATA:VOL:CLE")]
        head = f"SOUR{k}:DATA:ARB:DAC {name},"
        if transfer == "binary":
            cmds.append(Command(head, ieee_block(_i16_le(codes)),
                                f"IEEE 488.2 block, {codes.size} int16 little-endian codes, "
                                f"{2 * codes.size} bytes"))
        else:
            cmds.append(Command(head + ",".join(str(int(c)) for c in codes)))
        cmds += [Command(f"SOUR{k}:FUNC:ARB {name}"), Command(f"SOUR{k}:FUNC ARB"),
                 Command(f"SOUR{k}:FUNC:ARB:SRAT {_num(program.sample_rate_hz)}"),
                 Command(f"SOUR{k}:FUNC:ARB:FILT OFF"),  # sample and hold, as designed
                 Command(f"OUTP{k}:LOAD INF"),
                 Command(f"SOUR{k}:VOLT {_volts(sc.amplitude_vpp)}"),
                 Command(f"SOUR{k}:VOLT:OFFS {_volts(sc.offset_v)}")]
    s = program.sync_channel
    cmds += [Command("FUNC:ARB:SYNC"),  # restart both arbitrary waveforms together
             Command(f"SOUR{s}:MARK:POIN {program.marker_point}"),
             Command(f"OUTP:SYNC:SOUR CH{s}"), Command("OUTP:SYNC ON"),
             Command("OUTP1 ON"), Command("OUTP2 ON")]
    return cmds


RIGOL_DAC_MAX = 16383
"""Rigol DG 14-bit DAC code of the high level (0 is the low level)."""

RIGOL_PACKET_POINTS = 16384
"""Points per ``:TRACe:DATA:DAC16`` packet (DG800/DG900/DG1000Z guides: 8 to 16 kpts)."""


def _rigol(program: Program, transfer: str) -> list[Command]:
    cmds = [Command("*CLS")]
    for k in (1, 2):
        sc = program.scale(k)
        codes = np.round((sc.normalized + 1.0) / 2.0 * RIGOL_DAC_MAX).astype(np.int64)
        cmds += [Command(f":OUTPut{k} OFF"), Command(f":OUTPut{k}:LOAD INFinity")]
        if transfer == "binary":
            parts = [codes[i:i + RIGOL_PACKET_POINTS]
                     for i in range(0, codes.size, RIGOL_PACKET_POINTS)]
            for j, part in enumerate(parts):
                flag = "END" if j == len(parts) - 1 else "CON"
                cmds.append(Command(f":SOURce{k}:TRACe:DATA:DAC16 VOLATILE,{flag},",
                                    ieee_block(np.asarray(part, dtype="<u2").tobytes()),
                                    f"IEEE 488.2 block, {part.size} uint16 little-endian "
                                    f"codes 0-16383, {2 * part.size} bytes"))
        else:
            if codes.size > RIGOL_PACKET_POINTS:
                raise ValueError(f"Rigol :DATA:DAC takes at most {RIGOL_PACKET_POINTS} decimal "
                                 f"points, the program has {codes.size}; use binary")
            cmds.append(Command(f":SOURce{k}:TRACe:DATA:DAC VOLATILE,"
                                + ",".join(str(int(c)) for c in codes)))
        cmds.append(Command(f":SOURce{k}:APPLy:ARBitrary {_num(program.sample_rate_hz)},"
                            f"{_volts(sc.amplitude_vpp)},{_volts(sc.offset_v)}"))
    s = program.sync_channel
    cmds += [Command(":SOURce1:PHASe:SYNChronize"), Command(f":OUTPut{s}:SYNC ON"),
             Command(":OUTPut1 ON"), Command(":OUTPut2 ON")]
    return cmds


def _siglent(program: Program, transfer: str) -> list[Command]:
    cmds: list[Command] = []
    for k in (1, 2):
        sc, name = program.scale(k), program.names[k - 1]
        codes = sc.codes()
        cmds += [Command(f"C{k}:OUTP OFF"), Command(f"C{k}:OUTP LOAD,HZ"),
                 Command(f"C{k}:WVDT WVNM,{name},FREQ,{_num(program.frequency_hz)},"
                         f"AMPL,{_volts(sc.amplitude_vpp)},OFST,{_volts(sc.offset_v)},PHASE,0,"
                         "WAVEDATA,", _i16_le(codes),
                         f"{codes.size} int16 little-endian codes, {2 * codes.size} bytes"),
                 Command(f"C{k}:ARWV NAME,{name}"),
                 Command(f"C{k}:SRATE MODE,TARB,VALUE,{_num(program.sample_rate_hz)}"),
                 Command(f"C{k}:BSWV AMP,{_volts(sc.amplitude_vpp)},"
                         f"OFST,{_volts(sc.offset_v)}")]
    s = program.sync_channel
    cmds += [Command("MODE PHASELOCKED"), Command(f"C{s}:SYNC ON,TYPE,CH{s}"),
             Command("C1:OUTP ON"), Command("C2:OUTP ON")]
    return cmds


def _fields(answer: str) -> dict[str, str]:
    """``C1:BSWV WVTP,ARB,AMP,4V,...`` -> ``{"WVTP": "ARB", "AMP": "4V", ...}``."""
    body = answer.strip().split(" ", 1)[-1]
    parts = [p.strip() for p in body.split(",")]
    out = {"": parts[0]} if len(parts) % 2 else {}
    start = len(parts) % 2
    for i in range(start, len(parts) - 1, 2):
        out[parts[i].upper()] = parts[i + 1]
    return out


def _number(text: str | None) -> float | None:
    if text is None:
        return None
    m = re.match(r"\s*([-+]?\d*\.?\d+(?:[eE][-+]?\d+)?)", text)
    return float(m.group(1)) if m else None


def _close(got: float | None, want: float, *, abs_tol: float) -> bool:
    return got is not None and abs(got - want) <= abs_tol + 1e-4 * abs(want)


def _siglent_verify(program: Program) -> list[tuple[str, Check, str]]:
    checks: list[tuple[str, Check, str]] = []
    for k in (1, 2):
        sc, name = program.scale(k), program.names[k - 1]

        def arwv(ans: str, name: str = name, k: int = k) -> str | None:
            got = _fields(ans).get("NAME", "")
            return None if got.upper() == name.upper() else \
                f"expected NAME,{name} (the waveform written by C{k}:WVDT)"

        def srate(ans: str) -> str | None:
            f = _fields(ans)
            if f.get("MODE", "").upper() != "TARB":
                return "expected MODE,TARB"
            if not _close(_number(f.get("VALUE")), program.sample_rate_hz, abs_tol=1e-6):
                return f"expected VALUE,{_num(program.sample_rate_hz)}"
            return None

        def bswv(ans: str, sc: ChannelScale = sc) -> str | None:
            f = _fields(ans)
            if f.get("WVTP", "ARB").upper() != "ARB":
                return "expected WVTP,ARB"
            if not _close(_number(f.get("AMP")), sc.amplitude_vpp, abs_tol=1.5e-3):
                return f"expected AMP,{_volts(sc.amplitude_vpp)}V"
            if not _close(_number(f.get("OFST")), sc.offset_v, abs_tol=1.5e-3):
                return f"expected OFST,{_volts(sc.offset_v)}V"
            return None

        def outp(ans: str, k: int = k) -> str | None:
            f = _fields(ans)
            if f.get("", "").upper() != "ON":
                return "expected the output ON"
            if f.get("LOAD", "").upper() != "HZ":
                return "expected LOAD,HZ (high impedance)"
            return None

        checks += [(f"C{k}:ARWV?", arwv, f"C{k}:ARWV NAME,{name}"),
                   (f"C{k}:SRATE?", srate,
                    f"C{k}:SRATE MODE,TARB,VALUE,{_num(program.sample_rate_hz)}"),
                   (f"C{k}:BSWV?", bswv, f"C{k}:BSWV AMP,{_volts(sc.amplitude_vpp)},"
                                        f"OFST,{_volts(sc.offset_v)}"),
                   (f"C{k}:OUTP?", outp, f"C{k}:OUTP LOAD,HZ / C{k}:OUTP ON")]
    return checks


DIALECTS: dict[str, Dialect] = {
    "keysight": Dialect(
        name="keysight", title="Keysight 33500B/33600A",
        idn=re.compile(r"^(agilent|keysight)[^,]*,\s*33[56]\d\d[AB]\b", re.IGNORECASE),
        transfers=("binary", "ascii"), build=_keysight, error_query="SYST:ERR?",
        manual="Keysight 33500 Series Operating and Service Guide (SCPI programming "
               "reference: DATA:ARB:DAC, FUNC:ARB, FUNC:ARB:SRAT, FUNC:ARB:FILT, "
               "FUNC:ARB:SYNC, MARK:POIN, OUTP:SYNC, OUTP:LOAD, FORM:BORD, SYST:ERR?)"),
    "rigol": Dialect(
        name="rigol", title="Rigol DG800/DG900/DG1000Z/DG2000",
        idn=re.compile(r"^rigol[^,]*,\s*DG(8\d[02]|9\d2|1\d{3}Z|2\d{3})\b", re.IGNORECASE),
        transfers=("binary", "ascii"), build=_rigol, error_query=":SYSTem:ERRor?",
        manual="Rigol DG800 / DG900 / DG1000Z Programming Guides ([:SOURce<n>][:TRACe]:"
               "DATA:DAC16 and :DATA:DAC, :APPLy:ARBitrary, :PHASe:SYNChronize, "
               ":OUTPut<n>:LOAD, :OUTPut<n>:SYNC, :SYSTem:ERRor?)"),
    "siglent": Dialect(
        name="siglent", title="Siglent SDG1000X/SDG2000X/SDG6000X",
        idn=re.compile(r"^siglent[^,]*,\s*SDG\d{4}X", re.IGNORECASE),
        transfers=("binary",), build=_siglent, error_query=None, verify=_siglent_verify,
        manual="Siglent SDG Series Programming Guide (WVDT, ARWV, SRATE, BSWV, OUTP, SYNC, "
               "MODE); the SDG has no SCPI error queue"),
}


def detect_dialect(idn: str) -> Dialect:
    """The dialect of an instrument from its ``*IDN?`` answer.

    Raises ``GeneratorError`` naming the answer and the families known.
    """
    text = idn.strip()
    for d in DIALECTS.values():
        if d.idn.search(text):
            return d
    if re.search(r"rigol[^,]*,\s*DG8\d1\b", text, re.IGNORECASE):
        raise GeneratorError(f"*IDN? answered {text!r}: a single-channel Rigol DG800; the rig "
                             "needs two channels (one per panel)")
    known = "; ".join(d.title for d in DIALECTS.values())
    raise GeneratorError(f"*IDN? answered {text!r}: not a generator asynhdr knows how to "
                         f"program (known: {known}); pass --dialect to force one")


def scpi_commands(program: Program, dialect: str | Dialect, *,
                  transfer: str = "binary") -> list[Command]:
    """The command list that :func:`upload` sends, without an instrument."""
    d = dialect if isinstance(dialect, Dialect) else _get(dialect)
    return d.commands(program, transfer=transfer)


def _get(name: str) -> Dialect:
    try:
        return DIALECTS[name]
    except KeyError:
        raise ValueError(f"unknown dialect {name!r}; expected one of {sorted(DIALECTS)}"
                         ) from None


# --------------------------------------------------------------------------- upload

@dataclass(frozen=True)
class UploadReport:
    """What :func:`upload` did: the instrument, the dialect, the commands sent."""

    resource: str
    idn: str
    dialect: str
    commands: list[Command]
    verified: list[str]


def _open(resource: Any, visa_library: str, timeout_ms: int) -> tuple[Any, Callable[[], None]]:
    if not isinstance(resource, str):
        return resource, lambda: None  # an open pyvisa resource: the caller owns it
    try:
        import pyvisa
    except ImportError:
        raise GeneratorError("controlling a generator needs pyvisa: pip install "
                             "'asynhdr[generator]'") from None
    try:
        rm = pyvisa.ResourceManager(visa_library)
        inst: Any = rm.open_resource(resource)
    except (pyvisa.errors.Error, OSError, ValueError) as exc:
        raise GeneratorError(f"{resource}: cannot open the VISA resource ({exc})") from None
    inst.write_termination = "\n"
    inst.read_termination = "\n"
    inst.timeout = timeout_ms

    def close() -> None:
        inst.close()
        rm.close()

    return inst, close


def _errors(inst: Any, d: Dialect) -> list[str]:
    out: list[str] = []
    assert d.error_query is not None
    for _ in range(_MAX_ERRORS):
        ans = str(inst.query(d.error_query)).strip()
        if d.no_error.search(ans):
            return out
        out.append(ans)
    return out


def upload(
    resource: Any,
    program: Program,
    *,
    dialect: str | None = None,
    transfer: str = "binary",
    check_each: bool = True,
    visa_library: str = "",
    timeout_ms: int = DEFAULT_TIMEOUT_MS,
    progress: Callable[[int, int], None] | None = None,
) -> UploadReport:
    """Send ``program`` to the generator at ``resource`` and check that it took it.

    Parameters
    ----------
    resource : a VISA address (``"USB0::0x0957::0x2C07::MY5...::INSTR"``,
        ``"TCPIP0::192.168.1.5::INSTR"``) or an open pyvisa resource.
    program : the two channels (:class:`Program`).
    dialect : force a dialect name (else from ``*IDN?``).
    transfer : ``"binary"`` (IEEE 488.2 blocks) or ``"ascii"`` (decimal codes).
    check_each : read the error queue after every command (names the one rejected);
        else once at the end.
    visa_library : pyvisa backend (``""`` the default, ``"@py"`` pyvisa-py,
        ``"path/to/devices.yaml@sim"`` pyvisa-sim).
    progress : ``progress(done, total)`` after each command.

    Raises
    ------
    GeneratorError : the resource cannot be opened, ``*IDN?`` names an unknown
        instrument, a command left an error in the queue (named, with the errors), or a
        read-back disagrees (the command it checks is named).
    ValueError : a transfer the dialect does not take.
    """
    inst, close = _open(resource, visa_library, timeout_ms)
    label = resource if isinstance(resource, str) else str(getattr(inst, "resource_name", inst))
    try:
        idn = str(inst.query("*IDN?")).strip()
        if dialect is None:
            d = detect_dialect(idn)
        else:
            d = _get(dialect)
            if not d.idn.search(idn):
                logger.warning("%s: *IDN? answered %r, forced to the %s dialect", label, idn,
                               d.name)
        cmds = d.commands(program, transfer=transfer)
        if d.error_query is not None:
            stale = _errors(inst, d)  # left by earlier sessions: not ours to blame
            if stale:
                logger.warning("%s: %d errors were already queued before the upload: %s",
                               label, len(stale), "; ".join(stale))
        logger.info("%s: %s (%s dialect), %d commands", label, idn, d.name, len(cmds))
        for i, c in enumerate(cmds):
            if c.payload is None:
                inst.write(c.text)
            else:
                inst.write_raw(c.wire() + b"\n")
            if check_each and d.error_query is not None:
                errs = _errors(inst, d)
                if errs:
                    raise GeneratorError(f"{label}: the instrument rejected command "
                                         f"{c.show()!r}: {'; '.join(errs)}")
            if progress is not None:
                progress(i + 1, len(cmds))
        if d.error_query is not None:
            errs = _errors(inst, d)
            if errs:
                raise GeneratorError(f"{label}: the error queue is not empty after the upload: "
                                     f"{'; '.join(errs)}")
        verified = []
        for query, check, what in d.verify(program):
            ans = str(inst.query(query)).strip()
            problem = check(ans)
            if problem:
                raise GeneratorError(f"{label}: the instrument did not take command {what!r}: "
                                     f"{query} answered {ans!r}, {problem}")
            verified.append(query)
    except GeneratorError:
        raise
    except Exception as exc:  # pyvisa I/O errors, timeouts
        if type(exc).__module__.startswith("pyvisa"):
            raise GeneratorError(f"{label}: VISA error during the upload: {exc}") from exc
        raise
    finally:
        close()
    return UploadReport(resource=label, idn=idn, dialect=d.name, commands=cmds,
                        verified=verified)
