"""The last leg to the surface: a durable outbox, a framed and prioritised acoustic-modem
link with a byte budget, the surface receiver, a link simulator and health records."""
