"""The WC and a machine that is lost while its ME runs: the CMM at the far end of its serial line hangs
up, hangs, or is power-cycled (see gwc/wc/wc.py, gwc/me/cmm.py).

The ME says so (ME_LOST, with why) and goes on looking for the machine; the WC raises MACH_LOST with
the Cell Alarm Server, accepts no operation and has the Machine Server mark the machine Shutdown, so
MSCHED routes around it and a lot waiting for it is told. The WC stays started: the operator's
`gwc machine stop` still shuts it down for good (and the ME stops looking). When the ME hears the
machine again (ME_BACK) the WC clears its alarm, the machine is Idle and accepts its operations again.

The homing rule: the thesis homes the CMM when the operator starts its machine (ME_START raises
HOME_CMM, Listing 3). A machine coming back is not a start: no homing alarm is raised, so it comes
back by itself. A CMM whose controller lost power homes at its own power-on, before its Listing 9
program reads the line again; one that needs the operator is started again with `gwc machine stop`
and `gwc machine start`, which raise HOME_CMM as on any start. A stop while a start waits for its
HOME_CMM cancels that start: the WC withdraws the alarm ("start cancelled"), the ME stays shut down
(gwc/wc/runs.py, cancel_start).
"""

from __future__ import annotations

from gwc.errors import ConversationTimeout
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import MeMessage, MessageId
from gwc.ipc.names import Conv, Msg
from gwc.wc.base import ALL_OPERATIONS, SERVER_TIMEOUT, S
from gwc.wc.runs import WCRuns

LOST_ALARM = "MACH_LOST"


class WCDevice(WCRuns):
    """ME_LOST and ME_BACK: a machine lost and found while its ME runs."""

    lost: str | None = None  # why the machine does not answer its ME, while it does not
    _lost_alarm: int | None = None  # the MACH_LOST alarm raised for it, cleared when it is back

    def _from_me(self, msg: MeMessage) -> None:
        if msg.message_id == MessageId.ME_LOST:
            self._spawn(self.machine_lost(msg.alarm_text or "no reason given"))
        elif msg.message_id == MessageId.ME_BACK:
            self._spawn(self.machine_back())
        else:
            super()._from_me(msg)

    async def _go_shutdown(self, note: str, tell_me: bool = True) -> None:
        self.lost = None  # a machine shut down is not waited for (its MACH_LOST alarm stays for the operator)
        await super()._go_shutdown(note, tell_me)

    async def machine_lost(self, why: str) -> None:
        """The machine stopped answering its ME: alarm, no operations, Shutdown; the WC stays started.

        A run in progress was ended by the ME's RUN_COMPL (Run_Fail), sent before ME_LOST and completed
        first (the state lock is taken in turn). A machine already shut down (Run_Shut) is left so.
        """
        async with self._state_lock:
            if not self.started or self.lost is not None:
                self.log.warning("the ME lost the machine (%s) while it is %s: nothing to do", why, self.status)
                return
            self.lost = why
            self.log.error("machine %s lost (%s): alarm, Shutdown until it answers again", self.machine_id, why)
            self._lost_alarm = await self.raise_alarm(LOST_ALARM, f"{self.machine_id}: {why}", wait=False) or None
            if self.status == S.SETUP_SHUT:  # the operator asked for a shutdown: it is one now
                await self._go_shutdown(f"machine lost: {why}")
                return
            await self.set_accept_types([])
            if not await self.change_status(S.SHUTDOWN, note=f"machine lost: {why}"[:500]):
                self.status = S.SHUTDOWN  # we serve nothing now, whatever the Machine Server says
            self.machine_run_id = self.recipe_id = None

    async def machine_back(self) -> None:
        """The lost machine answers its ME again: alarm cleared, Idle, its operations accepted."""
        async with self._state_lock:
            if self.lost is None or not self.started:
                self.log.info("the ME hears its machine again; the machine is not waiting for it (%s)", self.status)
                return
            self.log.warning("machine %s answers again (it was lost: %s)", self.machine_id, self.lost)
            self.lost = None
            await self._clear_lost_alarm()
            if await self.change_status(S.IDLE, expect=[S.SHUTDOWN], note=None) and await self.set_accept_types(
                ALL_OPERATIONS
            ):
                self.log.info("machine %s is back: Idle, all operations accepted", self.machine_id)
                return
            await self._go_shutdown("the machine answers again but could not be brought back: start it again")

    async def _clear_lost_alarm(self) -> None:
        no, self._lost_alarm = self._lost_alarm, None
        if no is None:
            return
        try:
            answer = await self.ask(
                Conv.ALARM_CLR_REQ,
                message(Msg.ALARM_CLEAR_REQUEST, alarm_no=no, cleared_by=self.name),
                "cas",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            self.log.error("Cell Alarm Server did not answer the clearing of alarm %d", no)
            return
        if answer.ack_code == AckCode.ACK_OK:
            self.log.info("alarm %d (%s) cleared: the machine answers again", no, LOST_ALARM)
        else:  # the operator cleared it already
            self.log.info("alarm %d (%s) not cleared by us: %s %s", no, LOST_ALARM, answer.ack_code, answer.note or "")
