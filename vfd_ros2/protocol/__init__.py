"""Pure codecs and timing: how values look on the wire. No I/O, no profiles, no ROS.

``values`` (integer types, word order), ``registers`` (sign, 32-bit words, read
planning), ``scaling`` (rad/s at the output shaft <-> percent / Hz / rpm),
``rtu_timing`` (Modbus RTU character time, t3.5, frame sizes), ``cia402`` (the
CiA 402 state machine as enums and transitions).
"""
