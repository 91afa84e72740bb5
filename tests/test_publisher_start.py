"""The outputs a service puts at start: a backlog taken at once puts dozens of outputs on a new
key within milliseconds, before the new publisher's matching status has heard of the
subscribers that were there all along (a session just opened learns of them a moment later);
none of them may be lost for that."""

from __future__ import annotations

import threading

import zenoh

from service.transport.publisher import UNCONDITIONAL_PUTS, Publisher
from service.transport.session import ZenohOptions, open_session
from service.wire.keys import Keys
from service.wire.outgoing import Outgoing
from tests.support import wait_for

BURST = 5 * UNCONDITIONAL_PUTS
#: Services started afresh under the subscriber (how soon a new session hears of it varies).
STARTS = 5


def test_a_start_s_burst_reaches_a_subscriber_that_was_there_first(
    router: str, client: zenoh.Session
) -> None:
    keys = Keys("fusion")
    got: dict[str, int] = {}
    lock = threading.Lock()

    def heard(sample: zenoh.Sample) -> None:
        with lock:
            got[str(sample.key_expr)] = got.get(str(sample.key_expr), 0) + 1

    sub = client.declare_subscriber("fusion/radar/*/tracks", heard)
    try:
        for start in range(STARTS):
            service = open_session(ZenohOptions(mode="client", connect=(router,)))
            publisher = Publisher(keys, outbox_size=4)
            try:
                publisher.start(service)
                wanted = [keys.tracks(f"S{start}{rid}") for rid in "ABC"]
                # handed at once, each key's one after the other, as a start's backlog puts them
                publisher.hand([Outgoing(k, lambda i=i: {"n": i}) for k in wanted for i in range(BURST)])
                wait_for(lambda: all(got.get(k, 0) == BURST for k in wanted), timeout=10)  # noqa: B023
            finally:
                publisher.stop(5.0)
                service.close()
    finally:
        sub.undeclare()
