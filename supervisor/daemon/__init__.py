"""The supervisor as a daemon beside the robot controller: systemd notify, a local control socket, signals."""
