"""What crosses a socket: message types and codecs, socket creation, the shared frame ring,
JPEG, CURVE keys, and the clients of the control socket and the tap."""
