"""MAVLink 2 message signing on the flight-controller link (`[mavlink]
signing_key_file`).

With a key, every message we send is signed (SHA-256 based signature, link id
`signing_link_id`, timestamp in 10 us units since 2015 as pymavlink keeps it)
and every message we receive must carry a valid signature with the same key:
pymavlink turns an unsigned or wrongly signed one into BAD_DATA ("Invalid
signature"), which the feed ignores and counts. ArduPilot checks signatures
once a key is set on it (MAVProxy `signing setup PASSPHRASE`, or Mission
Planner); the same key goes in our file.

The key file: 64 hex digits (the 32-byte key), or a passphrase whose SHA-256
is the key (as MAVProxy derives it). It must belong to the service user and
be readable by it alone (mode 0600 or 0400): a key others can read signs for
anyone.
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path
from typing import Any

from onboard import NislamError


def load_signing_key(path: str | Path) -> bytes:
    """The 32-byte key in `path`; NislamError (one line) when the file is
    missing, open to others, or empty."""
    p = Path(path)
    try:
        st = p.stat()
        text = p.read_text(encoding="utf-8").strip()
    except OSError as e:
        raise NislamError(f"[mavlink] signing_key_file {p}: cannot read: {e.strerror}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise NislamError(f"[mavlink] signing_key_file {p}: mode {stat.S_IMODE(st.st_mode):04o} "
                          f"lets others read it; chmod 600 (owner only)")
    if st.st_uid != os.geteuid():
        raise NislamError(f"[mavlink] signing_key_file {p}: owned by uid {st.st_uid}, not by "
                          f"the service user (uid {os.geteuid()})")
    if not text:
        raise NislamError(f"[mavlink] signing_key_file {p}: empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode("utf-8")).digest()


def enable_signing(conn: Any, key: bytes, link_id: int) -> None:
    """Sign what `conn` (a pymavlink mavfile) sends; accept only messages
    signed with `key` (no unsigned callback: unsigned ones are refused)."""
    conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None, link_id=link_id)
