"""Inter-process communication: the CELL bus (multicast conversations) and the WC<->ME queues."""
