"""Structural checks of a log file before python-can reads it: its readers pass over a cut last
line, binary damage, a damaged frame line or a truncated BLF container silently; these find them,
say where, and give what is readable before the first fault (``read_log`` reports the rest)."""

from __future__ import annotations

import re
import zlib

__all__: list[str] = []

_ASC_KNOWN = re.compile(r"^(date |base |(no )?internal events logged|begin triggerblock|end triggerblock|//|"
                        r"\d+\.\d+\s+start of measurement)", re.IGNORECASE)
_HEX = "[0-9A-Fa-f]"
# what python-can's writers emit, line by line (anything else in a frame line is damage)
_LOG_LINE = re.compile(rf"^\(\d+(\.\d+)?\)\s+\S+\s+{_HEX}{{3}}({_HEX}{{5}})?#"
                       rf"(R\d*|#{_HEX}({_HEX}{{2}})*|({_HEX}{{2}})*)(\s+[RTrt])?$")
_ASC_DATA = re.compile(rf"^\d+\.\d+\s+\d+\s+{_HEX}+x?\s+(Rx|Tx)\s+d\s+({_HEX})((\s+{_HEX}{{2}})*)(\s.*)?$")
_ASC_OTHER_FRAME = re.compile(rf"^\d+\.\d+\s+(\d+\s+{_HEX}+x?\s+(Rx|Tx)\s+r(\s+{_HEX})?|\d+\s+ErrorFrame.*)$")
_CSV_LINE = re.compile(r"^[-+\d.eE]+,0x[0-9A-Fa-f]+,[01],[01],[01],(\d+),([A-Za-z0-9+/]*={0,2})$")


def _bad_lines(lines: list[str], suffix: str) -> tuple[list[int], list[int]]:
    """(indices of damaged frame lines, indices of timestamped non-frame lines) of a text log."""
    import base64
    import binascii

    bad, other = [], []
    for i, raw in enumerate(lines):
        ln = raw.strip()
        if not ln:
            continue
        if suffix == ".log":
            if not _LOG_LINE.match(ln):
                bad.append(i)
        elif suffix == ".csv":
            if i == 0 and ln.startswith("timestamp,"):
                continue
            m = _CSV_LINE.match(ln)
            if not m:
                bad.append(i)
                continue
            try:
                n = len(base64.b64decode(m.group(2), validate=True))
            except (binascii.Error, ValueError):
                bad.append(i)
                continue
            if n != int(m.group(1)) and m.group(2):
                bad.append(i)
        elif suffix == ".asc":
            if _ASC_KNOWN.match(ln) or _ASC_OTHER_FRAME.match(ln):
                continue
            m = _ASC_DATA.match(ln)
            if m:
                if len(m.group(3).split()) != int(m.group(2), 16):
                    bad.append(i)
            elif re.match(r"^\d+\.\d+\s", ln) and " Rx " not in f" {ln} " and " Tx " not in f" {ln} ":
                other.append(i)  # an event line (status, statistics, J1939): not a CAN frame
            else:
                bad.append(i)
    return bad, other


class _Fault(Exception):
    """A structural fault found while checking a file (internal)."""


def _blf_intact(raw: bytes, name: str) -> tuple[bytes, str | None]:
    """Check a BLF file's structure without trusting it: the header's file size and object count,
    every container's size, compression stream and declared length, every inner object's header.

    Returns:
        (blf bytes holding every complete object before the first fault, as one uncompressed
        container after the original header; the fault, or None).
    """
    from can.io import blf

    hdr = blf.FILE_HEADER_STRUCT
    if len(raw) == 0:
        raise _Fault(f"{name} is empty (0 bytes): not a BLF log")
    if len(raw) < hdr.size or raw[:4] != b"LOGG":
        raise _Fault(f"{name} is not a BLF log (no 'LOGG' signature in its first {hdr.size} bytes)")
    header = hdr.unpack_from(raw)
    header_size, file_size, object_count = header[1], header[10], header[12]
    if not hdr.size <= header_size <= len(raw):
        raise _Fault(f"{name}: BLF header size {header_size} is impossible for a {len(raw)}-byte file")
    base, cont = blf.OBJ_HEADER_BASE_STRUCT, blf.LOG_CONTAINER_STRUCT
    inner = bytearray()
    fault = None
    pos = header_size
    k = 0
    while pos < len(raw):
        if len(raw) - pos < base.size + cont.size:
            fault = f"truncated inside container {k} (byte {pos})"
            break
        sig, _, _, obj_size, obj_type = base.unpack_from(raw, pos)
        if sig != b"LOBJ" or obj_size < base.size + cont.size:
            fault = f"corrupted object header at byte {pos} (container {k})"
            break
        if obj_type != blf.LOG_CONTAINER:
            fault = f"object of type {obj_type} at byte {pos} where a log container was expected"
            break
        method, size = cont.unpack_from(raw, pos + base.size)
        payload = raw[pos + base.size + cont.size: pos + obj_size]
        short = pos + obj_size > len(raw)
        if method == blf.ZLIB_DEFLATE:
            z = zlib.decompressobj()
            try:
                data = z.decompress(payload)
            except zlib.error as e:
                fault = f"container {k} at byte {pos}: compressed data is damaged ({e})"
                break
            complete = z.eof and len(data) == size
        elif method == blf.NO_COMPRESSION:
            data = payload
            complete = len(data) == size
        else:
            fault = f"container {k} at byte {pos}: unknown compression method {method}"
            break
        if short or complete:
            inner += data  # a container cut by the end of the file: its decompressed prefix is intact
        if short or not complete:
            fault = (f"truncated inside container {k} (byte {pos}; {len(raw) - pos} of {obj_size} bytes present)"
                     if short else f"container {k} at byte {pos}: its data is damaged or incomplete")
            break
        pos += obj_size + obj_size % 4
        k += 1
    # keep the complete inner objects only, checking each header
    p, n_obj = 0, 0
    while p + base.size <= len(inner):
        sig, _, _, obj_size, _ = base.unpack_from(inner, p)
        if sig != b"LOBJ" or obj_size < base.size:
            fault = fault or f"corrupted frame object {n_obj} in the log's data"
            break
        if p + obj_size > len(inner):
            break
        p += obj_size + obj_size % 4
        n_obj += 1
    if p < len(inner) and fault is None:
        fault = f"{len(inner) - p} trailing bytes after the last complete object"
    if fault is None and file_size in (0, header_size) and len(raw) > header_size:
        fault = "the header was never finalized: the recording did not stop cleanly (all frames read)"
    if fault is None and file_size and file_size != len(raw):
        fault = f"the header says {file_size} bytes, the file has {len(raw)}"
    if fault is None and object_count and object_count != n_obj:
        fault = f"the header lists {object_count} objects, the file holds {n_obj}"
    body = bytes(inner[: min(p, len(inner))])
    obj_size = base.size + cont.size + len(body)
    rebuilt = (raw[:header_size] + base.pack(b"LOBJ", base.size, 1, obj_size, blf.LOG_CONTAINER)
               + cont.pack(blf.NO_COMPRESSION, len(body)) + body + b"\x00" * (obj_size % 4))
    return rebuilt, fault


def _text_checks(text: str, suffix: str, notes: list[str], name: str = "the file") -> tuple[list[str], str]:
    """Structural faults of a text log that python-can's readers pass over silently (a cut last
    line, binary bytes, a damaged frame line, a missing ASC end marker), and the text before the
    first fault (what is read). Event lines that are not CAN frames are added to ``notes``
    (reported, not a fault)."""
    faults = []
    lines = text.splitlines()
    keep = len(lines)
    if text and not text.endswith("\n"):
        tail = text.rsplit("\n", 1)[-1][:30]
        faults.append(f"the last line has no line end (the file was cut mid-line: {tail!r})")
        keep -= 1
    if "\ufffd" in text:
        faults.append(f"{text.count(chr(0xFFFD))} byte(s) are not text (binary damage)")
    bad, other = _bad_lines(lines, suffix)
    if bad and len(bad) == sum(1 for ln in lines if ln.strip()):  # not one line is a frame: another kind of file
        what = (f"{text.count(chr(0xFFFD))} byte(s) are not text" if "\ufffd" in text
                else f"first line: {lines[bad[0]].strip()[:30]!r}")
        raise _Fault(f"{name} is not a CAN log in python-can's {suffix} format: no line is a CAN frame ({what})")
    if bad:
        keep = min(keep, bad[0])
    if bad:
        faults.append(f"{len(bad)} damaged line(s) (first: line {bad[0] + 1}: {lines[bad[0]].strip()[:30]!r})")
    if other:
        notes.append(f"{len(other)} timestamped line(s) are events, not CAN frames; not read "
                     f"(first: line {other[0] + 1}: {lines[other[0]].strip()[:30]!r})")
    if suffix == ".asc" and text.strip():
        if not any(ln.strip().lower().startswith("end triggerblock") for ln in lines[-3:]):
            faults.append("no 'End TriggerBlock' line at the end: the file is truncated")
    return faults, ("\n".join(lines[:keep]) + "\n" if keep else "")
