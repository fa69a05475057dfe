"""Secrets never reach a log line: the redaction filter on our handler and uvicorn's loggers."""

from __future__ import annotations

import io
import logging

import pytest

from vloc.app import logs

TOKEN = "ZB8epzz8KZBn9JmGAjf_iTa85WMeWk_8iILEL3vPNkM"


@pytest.mark.parametrize(("text", "expected"), [
    (f"/v1/sessions/abc/stream?token={TOKEN}", "/v1/sessions/abc/stream?token=[redacted]"),
    (f"/x?a=1&token={TOKEN}&b=2", "/x?a=1&token=[redacted]&b=2"),
    (f"Authorization: Bearer {TOKEN}", "Authorization: Bearer [redacted]"),
    (f"X-API-Key: {TOKEN}", "X-API-Key: [redacted]"),
    (f"protocols vloc, vloc.token.{TOKEN}", "protocols vloc, vloc.token.[redacted]"),
    ("/v1/sessions/abc/poses?after_seq=3", "/v1/sessions/abc/poses?after_seq=3"),
])
def test_redact(text, expected):
    assert logs.redact(text) == expected


def test_uvicorn_websocket_line_is_redacted_in_place():
    """uvicorn logs the WebSocket's path with its query as an argument, and its access
    formatter unpacks the arguments: they stay a tuple of the same length."""
    logs.redact_uvicorn()
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    logger = logging.getLogger("uvicorn.error")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)
    try:
        logger.info('%s - "WebSocket %s" [accepted]', ("127.0.0.1", 5000),
                    f"/v1/sessions/s/stream?token={TOKEN}")
        access = logging.getLogger("uvicorn.access")
        record = access.makeRecord("uvicorn.access", logging.INFO, __file__, 1,
                                   '%s - "%s %s HTTP/%s" %d',
                                   ("127.0.0.1:5000", "GET", f"/s?token={TOKEN}", "1.1", 101),
                                   None)
        assert access.filter(record)
        assert len(record.args) == 5 and record.args[2] == "/s?token=[redacted]"
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert TOKEN not in out.getvalue() and "token=[redacted]" in out.getvalue()


@pytest.fixture
def configured():
    """``logs.configure`` for one test; the loggers it changes are put back after."""
    names = ("vloc", "app", "workers", "uvicorn", "uvicorn.error", "uvicorn.access")
    saved = {n: (logging.getLogger(n).handlers[:], logging.getLogger(n).level,
                 logging.getLogger(n).propagate, logging.getLogger(n).disabled) for n in names}
    logs.configure("INFO", json_lines=True)
    yield
    for n, (handlers, level, propagate, disabled) in saved.items():
        logger = logging.getLogger(n)
        logger.handlers[:], logger.level = handlers, level
        logger.propagate, logger.disabled = propagate, disabled


def test_our_handler_redacts_messages_and_fields(configured):
    out = io.StringIO()
    (handler,) = [h for h in logging.getLogger("vloc").handlers
                  if any(isinstance(f, logs.RedactSecrets) for f in h.filters)]
    handler.setStream(out)
    logging.getLogger("vloc.test").info("client sent %s", f"Bearer {TOKEN}",
                                        extra={"url": f"/a?token={TOKEN}"})
    err = out.getvalue()
    assert TOKEN not in err and err.count("[redacted]") == 2


def test_json_lines_carry_no_terminal_colour_copy():
    record = logging.makeLogRecord({"name": "uvicorn.error", "levelname": "INFO",
                                    "msg": "Started server process [%d]", "args": (7,),
                                    "color_message": "Started server process [\x1b[36m%d\x1b[0m]"})
    line = logs.JsonFormatter().format(record)
    assert "color_message" not in line and "\\u001b" not in line
    assert '"msg": "Started server process [7]"' in line
