"""Signal generator upload: SCPI per dialect, against pyvisa-sim instruments.

The simulated instruments live in ``tests/instruments/generators.yaml``: each accepts
exactly its dialect's commands and puts any other in its error queue (Keysight, Rigol),
or is checked by reading its state back (Siglent). pyvisa-sim matches text messages only,
so :func:`binary_sim` strips binary payloads (IEEE 488.2 definite-length blocks, Siglent
``WAVEDATA`` bytes) before the simulator matches the command, and keeps them; the tests
decode them here, independently of the code under test.

What the simulator cannot check: the instruments' own parsing of the binary data (byte
order, code range) and timing. Those are checked here against the manuals' definitions
(decoded by hand below), not against an instrument.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import pyvisa
from pyvisa_sim.devices import Device
from typer.testing import CliRunner

import asynhdr.cli.generator  # noqa: F401  (registers the command)
from asynhdr.cli import app
from asynhdr.generator import (
    DIALECTS,
    GeneratorError,
    Program,
    detect_dialect,
    ieee_block,
    scpi_commands,
    upload,
)
from asynhdr.panel import get_panel
from asynhdr.rig import Rig
from asynhdr.waveform import design

YAML = Path(__file__).parent / "instruments" / "generators.yaml"
SIM = f"{YAML}@sim"
KEYSIGHT = "USB0::0x0957::0x2C07::MY00000001::INSTR"
RIGOL = "USB0::0x1AB1::0x0642::DG1ZA000000001::INSTR"
SIGLENT = "USB0::0xF4EC::0x1102::SDG2XCAQ000001::INSTR"
SIGLENT_STUCK = "USB0::0xF4EC::0x1103::SDG1XCAQ000002::INSTR"
ACME = "TCPIP0::192.0.2.7::INSTR"
RIGOL_SINGLE = "USB0::0x1AB1::0x0643::DG8A000000003::INSTR"

_BLOCK = re.compile(rb",#([1-9])")


@pytest.fixture
def binary_sim(monkeypatch):
    """pyvisa-sim devices that take binary payloads: each is replaced by a marker and kept
    in ``device.payloads`` as ``(command text, bytes)``."""
    original = Device.write

    def write(self, data: bytes) -> None:
        store = self.__dict__.setdefault("payloads", [])
        i = data.find(b"WAVEDATA,")
        if i >= 0:
            head, payload = data[:i + 9], data[i + 9:]
            assert payload.endswith(b"\n")
            store.append((head.decode("ascii"), payload[:-1]))
            return original(self, head + b"<binary>\n")
        m = _BLOCK.search(data)
        if m:
            nd = int(m.group(1))
            start = m.end() + nd
            length = int(data[m.end():start])
            store.append((data[:m.start() + 1].decode("ascii"), data[start:start + length]))
            assert data[start + length:] == b"\n", "bytes after the declared block length"
            return original(self, data[:m.start() + 1] + b"<block>\n")
        return original(self, data)

    monkeypatch.setattr(Device, "write", write)


def _open(address):
    rm = pyvisa.ResourceManager(SIM)
    inst = rm.open_resource(address, write_termination="\n", read_termination="\n")
    device = rm.visalib.sessions[inst.session].device
    return rm, inst, device


def _program(**kw) -> Program:
    rig = Rig()
    t1, t2 = rig.waveforms()
    d = design(t1, t2, panel1=get_panel("tn_generic"), panel2=get_panel("tn_generic_nb"),
               period_us=rig.period_us, sample_rate_hz=200_000.0,
               ramp_fraction=rig.ramp_fraction, **kw)
    return Program.from_design(d)


@pytest.fixture(scope="module")
def program() -> Program:
    return _program()


def _expected_i16(v: np.ndarray) -> np.ndarray:
    # written out from the definition: full scale +-32767 at the channel's extremes
    hi, lo = v.max(), v.min()
    return np.round((v - (hi + lo) / 2) / ((hi - lo) / 2) * 32767).astype(np.int64)


def _decode_block(block: bytes) -> bytes:
    assert block[:1] == b"#"
    nd = int(block[1:2])
    n = int(block[2:2 + nd])
    assert len(block) == 2 + nd + n
    return block[2 + nd:]


def _prop(device, name):
    return device._properties[name].get_value()


def test_ieee_block_by_hand():
    assert ieee_block(b"abcd") == b"#14abcd"
    assert ieee_block(bytes(12)) == b"#212" + bytes(12)
    assert _decode_block(ieee_block(bytes(range(200)))) == bytes(range(200))


def test_program_checks(program):
    assert program.n_samples == 10_000 and program.frequency_hz == 20.0
    sc = program.scale(1)
    v = program.voltage_v[0]
    assert sc.amplitude_vpp == pytest.approx(v.max() - v.min())
    assert sc.offset_v == pytest.approx(0.0, abs=1e-12)  # AC carrier: symmetric
    with pytest.raises(ValueError, match="same number of samples"):
        Program(voltage_v=(np.zeros(10), np.zeros(12)), sample_rate_hz=10.0, period_us=1)
    with pytest.raises(ValueError, match="do not make"):
        Program(voltage_v=(np.zeros(10), np.zeros(10)), sample_rate_hz=1000.0, period_us=50)
    with pytest.raises(ValueError, match="waveform name"):
        Program(voltage_v=(np.zeros(10), np.zeros(10)), sample_rate_hz=1e6, period_us=10,
                names=("1bad", "ok"))


def test_detect_dialect_from_idn():
    assert detect_dialect("Agilent Technologies,33522B,MY52400835,3.03-1.19").name == \
        "keysight"
    assert detect_dialect("Keysight Technologies,33622A,MY5,A.02").name == "keysight"
    assert detect_dialect("Rigol Technologies,DG1062Z,DG1ZA,00.01.14").name == "rigol"
    assert detect_dialect("RIGOL TECHNOLOGIES,DG992,DG9A,00.02").name == "rigol"
    assert detect_dialect("Siglent Technologies,SDG6022X,SDG6X,6.01").name == "siglent"
    with pytest.raises(GeneratorError, match="not a generator asynhdr knows"):
        detect_dialect("Tektronix,AFG31022,C0,1.0")
    with pytest.raises(GeneratorError, match="single-channel"):
        detect_dialect("Rigol Technologies,DG811,DG8A,00.01")


def test_keysight_sequence_and_block(program):
    cmds = scpi_commands(program, "keysight")
    texts = [c.text for c in cmds]
    # order matters: data, then select it, then rate, load before amplitude, sync, outputs
    for k in (1, 2):
        i_data = texts.index(f"SOUR{k}:DATA:ARB:DAC ASYNHDR{k},")
        assert texts.index(f"SOUR{k}:DATA:VOL:CLE") < i_data < \
            texts.index(f"SOUR{k}:FUNC:ARB ASYNHDR{k}") < texts.index(f"SOUR{k}:FUNC ARB")
        assert texts.index(f"OUTP{k}:LOAD INF") < texts.index(f"SOUR{k}:VOLT 10.000000")
        assert texts.index(f"OUTP{k} OFF") < i_data
        codes = np.frombuffer(_decode_block(cmds[i_data].payload), dtype="<i2")
        np.testing.assert_array_equal(codes, _expected_i16(program.voltage_v[k - 1]))
    assert texts.index("FORM:BORD SWAP") < texts.index("SOUR1:DATA:ARB:DAC ASYNHDR1,")
    assert texts[-6:] == ["FUNC:ARB:SYNC", "SOUR1:MARK:POIN 5000", "OUTP:SYNC:SOUR CH1",
                          "OUTP:SYNC ON", "OUTP1 ON", "OUTP2 ON"]
    assert "SOUR1:FUNC:ARB:SRAT 200000" in texts
    ascii_cmds = scpi_commands(program, "keysight", transfer="ascii")
    assert "FORM:BORD SWAP" not in [c.text for c in ascii_cmds]
    data = next(c.text for c in ascii_cmds if c.text.startswith("SOUR2:DATA:ARB:DAC"))
    values = np.array(data.split(",", 1)[1].split(","), dtype=np.int64)
    np.testing.assert_array_equal(values, _expected_i16(program.voltage_v[1]))


def test_rigol_codes_and_packets(program):
    cmds = scpi_commands(program, "rigol")
    data = [c for c in cmds if c.payload is not None]
    assert [c.text for c in data] == [":SOURce1:TRACe:DATA:DAC16 VOLATILE,END,",
                                      ":SOURce2:TRACe:DATA:DAC16 VOLATILE,END,"]
    v = program.voltage_v[0]
    want = np.round((v - v.min()) / (v.max() - v.min()) * 16383).astype(np.int64)
    got = np.frombuffer(_decode_block(data[0].payload), dtype="<u2")
    np.testing.assert_array_equal(got, want)
    assert got.min() == 0 and got.max() == 16383
    # 40,000 points: three packets of at most 16 kpts, CON, CON, END
    long = Program(voltage_v=(np.sin(np.arange(40_000) / 50.0), np.cos(np.arange(40_000) / 50.0)),
                   sample_rate_hz=800_000.0, period_us=50_000)
    packets = [c for c in scpi_commands(long, "rigol") if c.text.startswith(":SOURce1:TRACe")]
    assert [c.text.split(",")[1] for c in packets] == ["CON", "CON", "END"]
    assert sum(len(_decode_block(c.payload)) for c in packets) == 80_000
    with pytest.raises(ValueError, match="at most 16384 decimal points"):
        scpi_commands(long, "rigol", transfer="ascii")


def test_siglent_has_only_binary(program):
    cmds = scpi_commands(program, "siglent")
    wv = [c for c in cmds if c.payload is not None]
    assert wv[0].text.startswith("C1:WVDT WVNM,ASYNHDR1,FREQ,20,AMPL,")
    assert wv[0].text.endswith(",PHASE,0,WAVEDATA,")
    np.testing.assert_array_equal(np.frombuffer(wv[1].payload, dtype="<i2"),
                                  _expected_i16(program.voltage_v[1]))
    with pytest.raises(ValueError, match="only as binary"):
        scpi_commands(program, "siglent", transfer="ascii")


# --- against the simulated instruments ---------------------------------------------------

@pytest.mark.parametrize("transfer", ["binary", "ascii"])
def test_upload_keysight_sim(binary_sim, program, transfer):
    rm, inst, device = _open(KEYSIGHT)
    try:
        report = upload(inst, program, transfer=transfer)
    finally:
        rm.close()
    assert report.dialect == "keysight" and report.idn.startswith("Keysight Technologies,33522B")
    assert [c.text for c in report.commands] == \
        [c.text for c in scpi_commands(program, "keysight", transfer=transfer)]
    for k in (1, 2):
        want = _expected_i16(program.voltage_v[k - 1])
        if transfer == "binary":
            head, data = device.payloads[k - 1]
            assert head == f"SOUR{k}:DATA:ARB:DAC ASYNHDR{k},"
            np.testing.assert_array_equal(np.frombuffer(data, dtype="<i2"), want)
        else:
            got = np.array(_prop(device, f"ascii_data{k}").split(","), dtype=np.int64)
            np.testing.assert_array_equal(got, want)
        assert _prop(device, f"srate{k}") == 200_000.0
        assert _prop(device, f"volt{k}") == pytest.approx(program.scale(k).amplitude_vpp,
                                                          abs=1e-6)
    assert _prop(device, "marker1") == 5000


@pytest.mark.parametrize("transfer", ["binary", "ascii"])
def test_upload_rigol_sim(binary_sim, program, transfer):
    rm, inst, device = _open(RIGOL)
    try:
        report = upload(inst, program, transfer=transfer)
    finally:
        rm.close()
    assert report.dialect == "rigol"
    v = program.voltage_v[1]
    want = np.round((v - v.min()) / (v.max() - v.min()) * 16383).astype(np.int64)
    if transfer == "binary":
        np.testing.assert_array_equal(np.frombuffer(device.payloads[1][1], dtype="<u2"), want)
    else:
        np.testing.assert_array_equal(
            np.array(_prop(device, "ascii_data2").split(","), dtype=np.int64), want)
    rate, vpp, off = (float(x) for x in _prop(device, "apply2").split(","))
    assert rate == 200_000.0 and vpp == pytest.approx(v.max() - v.min(), abs=1e-6)
    assert off == pytest.approx((v.max() + v.min()) / 2, abs=1e-6)


def test_upload_siglent_sim_reads_back(binary_sim, program):
    rm, inst, device = _open(SIGLENT)
    try:
        report = upload(inst, program)
    finally:
        rm.close()
    assert report.dialect == "siglent"
    assert report.verified == ["C1:ARWV?", "C1:SRATE?", "C1:BSWV?", "C1:OUTP?",
                               "C2:ARWV?", "C2:SRATE?", "C2:BSWV?", "C2:OUTP?"]
    np.testing.assert_array_equal(np.frombuffer(device.payloads[0][1], dtype="<i2"),
                                  _expected_i16(program.voltage_v[0]))
    assert _prop(device, "arwv2") == "ASYNHDR2" and _prop(device, "outp1") == "ON"


def test_siglent_readback_names_the_command(binary_sim, program):
    # this instrument keeps playing a built-in waveform whatever ARWV says
    with pytest.raises(GeneratorError, match=r"did not take command 'C1:ARWV NAME,ASYNHDR1'"
                                             r".*StairUp"):
        upload(SIGLENT_STUCK, program, visa_library=SIM)


def test_rejected_command_is_named(binary_sim):
    # 30 V peaks: 60 Vpp, beyond the 33522B's 20 Vpp into high impedance
    p = Program(voltage_v=(30 * np.sin(np.arange(100) / 5.0), np.cos(np.arange(100) / 5.0)),
                sample_rate_hz=1e6, period_us=100)
    with pytest.raises(GeneratorError) as exc:
        upload(KEYSIGHT, p, visa_library=SIM)
    msg = str(exc.value)
    assert "rejected command 'SOUR1:VOLT 59." in msg and '-113,"Undefined header"' in msg
    assert KEYSIGHT in msg


def test_wrong_sequence_is_rejected(binary_sim, program):
    # Rigol commands sent to the Keysight: the first one it does not know is named
    with pytest.raises(GeneratorError, match=r"rejected command ':OUTPut1 OFF'"):
        upload(KEYSIGHT, program, dialect="rigol", visa_library=SIM)
    # without the per-command check the queue is still read at the end
    with pytest.raises(GeneratorError, match="error queue is not empty after the upload"):
        upload(KEYSIGHT, program, dialect="rigol", visa_library=SIM, check_each=False)


def test_unknown_instruments(binary_sim, program):
    with pytest.raises(GeneratorError, match=r"'ACME Instruments,XG-1,0001,1.0': not a "
                                             "generator asynhdr knows"):
        upload(ACME, program, visa_library=SIM)
    with pytest.raises(GeneratorError, match="single-channel"):
        upload(RIGOL_SINGLE, program, visa_library=SIM)


def test_every_dialect_has_a_manual():
    for d in DIALECTS.values():
        assert d.manual and d.title and d.transfers


# --- command line ----------------------------------------------------------------------

def test_cli_upload_and_dry_run(binary_sim, tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["generator", "upload", "--resource", SIGLENT, "--visa-library",
                              SIM])
    assert res.exit_code == 0, res.output
    out = " ".join(res.output.split())
    assert "AC carrier 1000 Hz" in out and "16 commands (siglent dialect, binary) accepted" \
        in out and "read back C1:ARWV?" in out
    dry = runner.invoke(app, ["generator", "upload", "--dry-run"])
    assert dry.exit_code == 0, dry.output
    for line in ("SOUR1:DATA:ARB:DAC ASYNHDR1,<IEEE 488.2 block, 10000 int16",
                 ":SOURce2:TRACe:DATA:DAC16 VOLATILE,END,<IEEE 488.2 block",
                 "C1:SRATE MODE,TARB,VALUE,200000", "FUNC:ARB:SYNC", "C2:BSWV?"):
        assert line in dry.output
    # files written by `asynhdr waveform --dc` drive the upload, with a warning
    assert runner.invoke(app, ["waveform", "--out", str(tmp_path), "--dc"]).exit_code == 0
    dc = runner.invoke(app, ["generator", "upload", "--design", str(tmp_path), "--dry-run",
                             "--dialect", "keysight", "--transfer", "ascii"])
    assert dc.exit_code == 0, dc.output
    assert "DC" in dc.output and "degrades" in " ".join(dc.output.split())
    assert "SOUR1:VOLT:OFFS 2.5" in dc.output  # a 0-5 V drive around 2.5 V
    bad = runner.invoke(app, ["generator", "upload", "--resource", ACME, "--visa-library",
                              SIM])
    assert bad.exit_code == 2
    assert "not a generator asynhdr knows" in " ".join(bad.output.split())
    none = runner.invoke(app, ["generator", "upload"])
    assert none.exit_code == 2 and "--resource" in none.output
