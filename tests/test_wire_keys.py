"""Key expressions, schemas and the JSON envelope of the wire format (contracts/wire_keys.py)."""
import pytest
from tensortouch.contracts.wire_keys import (
    ENCODINGS,
    NonFiniteError,
    WireError,
    check_encoding,
    dumps,
    key,
    loads,
    need,
    parse_key,
    schema_of,
)


def test_key_round_trip_and_wildcards():
    assert key("left-1", "fields") == "tensortouch/left-1/fields"
    assert parse_key("tensortouch/left-1/contacts") == ("left-1", "contacts")
    assert key("*", "status") == "tensortouch/*/status"
    with pytest.raises(WireError, match="key kind 'pressure'"):
        key("left-1", "pressure")
    with pytest.raises(WireError, match="sensor id 'a/b'"):
        key("a/b", "fields")
    with pytest.raises(WireError, match="expected 'tensortouch/<sensor-id>/<kind>'"):
        parse_key("other/left-1/fields")


def test_encoding_carries_the_schema():
    assert ENCODINGS["contacts"] == "application/json;tensortouch.contacts.v1"
    assert schema_of(ENCODINGS["fields"]) == "tensortouch.fields.v1" and schema_of("text/plain") is None
    check_encoding("fields", ENCODINGS["fields"])
    check_encoding("fields", None)
    with pytest.raises(WireError, match="expected 'tensortouch.wrench.v1'"):
        check_encoding("wrench", ENCODINGS["status"])


def test_json_envelope_rejects_non_finite_numbers_both_ways():
    body = {"schema": "tensortouch.status.v1", "n": 3, "x": 0.5}
    assert dumps(body) == b'{"schema":"tensortouch.status.v1","n":3,"x":0.5}'
    assert loads("status", dumps(body)) == body
    assert dumps({"x": float("nan")}, strict=False) == b'{"x":null}'
    with pytest.raises(WireError, match="non-finite number nan"):
        dumps({"x": float("nan")})
    with pytest.raises(NonFiniteError, match="NaN"):
        loads("status", b'{"schema":"tensortouch.status.v1","x":NaN}')
    with pytest.raises(NonFiniteError, match="beyond the float range"):
        loads("status", b'{"schema":"tensortouch.status.v1","x":1e999}')
    with pytest.raises(WireError, match="expected a JSON object, got list"):
        loads("status", b"[1]")
    with pytest.raises(WireError, match="missing field 'n'"):
        need("status", {}, "n")
