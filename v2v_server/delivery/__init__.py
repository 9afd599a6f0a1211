"""The delivery state machines, pure and clocked from outside: what each epoch owes (scheduler),
what each consumer holds (ledger), both with batching (core), and the acknowledgement journal."""
