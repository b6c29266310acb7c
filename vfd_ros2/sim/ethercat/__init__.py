"""A simulated EtherCAT segment: slave controllers that a real master (SOEM) brings to OP.

``frame`` (codec), ``sii`` (EEPROM images), ``objects``/``mailbox``/``coe`` (CoE
server), ``esc`` (one slave controller and its stack), ``application`` (the
interface to device firmware), ``drive`` (a CiA 402 velocity drive as data),
``catalog`` (drive families), ``segment`` (ESCs on a raw interface, in a process).
"""
