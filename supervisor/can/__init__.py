"""The CAN side channel to the cell's safety PLC (RELIABILITY.md: heartbeat, E2E, bus faults).

- `settings`: the `can:` config section (interface, frame ids, data ids, periods), parsed once.
- `e2e`: alive counter + CRC-8 (SAE J1850) over the data ID and the payload; the receiver's checks.
- `codec`: the shipped DBC (`config/can/supervisor.dbc`) through cantools, with E2E protection.
- `channel`: the supervisor's end: heartbeat (driven by the control loop), STOP on every brake,
  the PLC's EXTERNAL_STOP input, bus-fault detection.
- `monitor`: a heartbeat consumer (`supervisor can monitor`) that trips after its timeout.
"""
