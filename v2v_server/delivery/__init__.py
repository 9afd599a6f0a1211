"""Delivery by plan, pure and clocked from outside: what workers make ahead of the readers'
fetches and what a fetch is answered with (``plan_schedule``), and the delivery settings (``policy``)."""
