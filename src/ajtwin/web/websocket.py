"""The dashboard's websocket transport: uvicorn's sans-I/O websockets protocol, made to
answer every opening request, and the server options every dashboard runs with.

Two client errors uvicorn (0.54) handles badly are handled here. uvicorn hands a
websocket upgrade request to ``websockets``' sans-I/O parser. When that parser refuses
the request (a header value with a control character, a request line or header block too
long, …) it prepares a 4xx answer or an end of stream, but uvicorn writes out only what
follows a *parsed* request: the client then waits forever on an open connection (found
by ``tests/test_fuzz_ws.py``). :class:`DashboardWebSocketProtocol` writes what the
parser prepared — or, when it prepared no answer, a 400 with a sentence — and closes the
connection. A text message that is not UTF-8 is closed with 1007 (as uvicorn does) but
logged in one line, not as a traceback.

:data:`SERVER_OPTIONS` are the uvicorn options of ``ajtwin dashboard`` and of
:class:`ajtwin.web.server.BackgroundServer` alike: this protocol, and a 64 KiB limit on
a message from a page (the pages send none; uvicorn's default, 16 MiB, is memory an
anonymous client could make the server hold per connection).

Example
-------
>>> import uvicorn                                                  # doctest: +SKIP
>>> uvicorn.run(app, host="127.0.0.1", port=8050, **SERVER_OPTIONS)  # doctest: +SKIP
"""

from __future__ import annotations

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

#: the largest message a page may send [bytes] (it sends none; a larger one closes 1009)
MAX_MESSAGE_BYTES = 64 * 1024

_BAD_REQUEST = (
    b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain; charset=utf-8\r\n"
    b"Connection: close\r\nContent-Length: %d\r\n\r\n%s"
)


class DashboardWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websockets sans-I/O protocol that always answers the opening request
    and closes a text message that is not UTF-8 with 1007 and one log line (uvicorn logs
    a traceback for that client error)."""

    def send_receive_event_to_app(self) -> None:
        """Hand a received message to the app unless the connection is already closing."""
        if self.conn.state is not State.OPEN:
            # the same read also brought the client's close (websockets is already
            # closing): the message is moot, the close frame is answered next
            self.frames = []
            return
        if self.curr_msg_data_type == "text" and not self.close_sent:
            try:
                b"".join(self.frames).decode("utf-8")
            except UnicodeDecodeError:
                self.frames = []
                self.logger.warning(
                    "websocket %s: a text message that is not UTF-8; closed", self.client
                )
                self.conn.send_close(1007, "a text message that is not UTF-8")
                self.handle_parser_exception()
                return
        super().send_receive_event_to_app()

    def data_received(self, data: bytes) -> None:
        """Feed received bytes; a refused opening request gets websockets' answer and is closed."""
        super().data_received(data)
        if self.handshake_initiated or self.conn.handshake_exc is None:
            return
        # the request was refused before uvicorn saw it: send what websockets prepared
        output = b"".join(self.conn.data_to_send())
        if not output.startswith(b"HTTP/"):
            reason = f"not a valid websocket opening request ({self.conn.handshake_exc})\n"
            body = reason.encode("utf-8", "replace")
            output = _BAD_REQUEST % (len(body), body)
        self.handshake_initiated = self.handshake_complete = self.close_sent = True
        if not self.transport.is_closing():
            self.transport.write(output)
            self.transport.close()


#: uvicorn options of every dashboard server (module docstring)
SERVER_OPTIONS = {"ws": DashboardWebSocketProtocol, "ws_max_size": MAX_MESSAGE_BYTES}
