"""EtherCAT numbers shared by the master link and the simulated segment (pure, no I/O).

What the wire and the slave controller's registers mean: AL states and AL
status codes (ETG.1000.6), the ESC register addresses a master touches
(ETG.1000.4 section 6; Beckhoff ESC datasheet section II, which follows it),
mailbox and CoE numbers (ETG.1000.6 section 5.6), and the CiA 301 SDO abort
codes an EtherCAT slave answers with (ETG.1000.6 table 43 repeats them).
Both sides import this module, so a code is spelt once.
"""

from __future__ import annotations

import enum

#: EtherType of EtherCAT frames (ETG.1000.4 5.2)
ETHERTYPE_ETHERCAT = 0x88A4


class ALState(enum.IntEnum):
    """Application-layer states in AL control / AL status (ETG.1000.6 6.4.1)."""

    NONE = 0x00
    INIT = 0x01
    PRE_OP = 0x02
    BOOT = 0x03
    SAFE_OP = 0x04
    OP = 0x08


#: bit 4 of AL control (error acknowledge) and of AL status (error indication)
AL_ERROR_FLAG = 0x10
AL_STATE_MASK = 0x0F


class ALStatusCode(enum.IntEnum):
    """AL status codes in register 0x0134 (ETG.1000.6 table 11)."""

    NO_ERROR = 0x0000
    UNSPECIFIED_ERROR = 0x0001
    NO_MEMORY = 0x0002
    INVALID_REQUESTED_STATE_CHANGE = 0x0011
    UNKNOWN_REQUESTED_STATE = 0x0012
    BOOTSTRAP_NOT_SUPPORTED = 0x0013
    NO_VALID_FIRMWARE = 0x0014
    INVALID_MAILBOX_CONFIGURATION_BOOT = 0x0015
    INVALID_MAILBOX_CONFIGURATION = 0x0016
    INVALID_SYNC_MANAGER_CONFIGURATION = 0x0017
    NO_VALID_INPUTS = 0x0018
    NO_VALID_OUTPUTS = 0x0019
    SYNCHRONIZATION_ERROR = 0x001A
    SYNC_MANAGER_WATCHDOG = 0x001B
    INVALID_SYNC_MANAGER_TYPES = 0x001C
    INVALID_OUTPUT_CONFIGURATION = 0x001D
    INVALID_INPUT_CONFIGURATION = 0x001E
    INVALID_WATCHDOG_CONFIGURATION = 0x001F
    SLAVE_NEEDS_COLD_START = 0x0020
    SLAVE_NEEDS_INIT = 0x0021
    SLAVE_NEEDS_PRE_OP = 0x0022
    SLAVE_NEEDS_SAFE_OP = 0x0023
    INVALID_INPUT_MAPPING = 0x0024
    INVALID_OUTPUT_MAPPING = 0x0025
    INCONSISTENT_SETTINGS = 0x0026
    FREE_RUN_NOT_SUPPORTED = 0x0027
    SYNCHRONIZATION_NOT_SUPPORTED = 0x0028
    FREE_RUN_NEEDS_3_BUFFER_MODE = 0x0029
    BACKGROUND_WATCHDOG = 0x002A
    NO_VALID_INPUTS_AND_OUTPUTS = 0x002B
    FATAL_SYNC_ERROR = 0x002C
    NO_SYNC_ERROR = 0x002D
    INVALID_DC_SYNC_CONFIGURATION = 0x0030
    INVALID_DC_LATCH_CONFIGURATION = 0x0031
    PLL_ERROR = 0x0032
    DC_SYNC_IO_ERROR = 0x0033
    DC_SYNC_TIMEOUT = 0x0034
    DC_INVALID_SYNC_CYCLE_TIME = 0x0035
    DC_INVALID_SYNC0_CYCLE_TIME = 0x0036
    DC_INVALID_SYNC1_CYCLE_TIME = 0x0037


AL_STATUS_TEXT: dict[int, str] = {
    0x0000: 'No error',
    0x0001: 'Unspecified error',
    0x0002: 'No memory',
    0x0011: 'Invalid requested state change',
    0x0012: 'Unknown requested state',
    0x0013: 'Bootstrap not supported',
    0x0014: 'No valid firmware',
    0x0015: 'Invalid mailbox configuration (bootstrap)',
    0x0016: 'Invalid mailbox configuration',
    0x0017: 'Invalid sync manager configuration',
    0x0018: 'No valid inputs available',
    0x0019: 'No valid outputs',
    0x001A: 'Synchronization error',
    0x001B: 'Sync manager watchdog',
    0x001C: 'Invalid sync manager types',
    0x001D: 'Invalid output configuration',
    0x001E: 'Invalid input configuration',
    0x001F: 'Invalid watchdog configuration',
    0x0020: 'Slave needs cold start',
    0x0021: 'Slave needs INIT',
    0x0022: 'Slave needs PREOP',
    0x0023: 'Slave needs SAFEOP',
    0x0024: 'Invalid input mapping',
    0x0025: 'Invalid output mapping',
    0x0026: 'Inconsistent settings',
    0x0027: 'Free run not supported',
    0x0028: 'Synchronization not supported',
    0x0029: 'Free run needs 3-buffer mode',
    0x002A: 'Background watchdog',
    0x002B: 'No valid inputs and outputs',
    0x002C: 'Fatal sync error',
    0x002D: 'No sync error',
    0x0030: 'Invalid DC SYNC configuration',
    0x0031: 'Invalid DC latch configuration',
    0x0032: 'PLL error',
    0x0033: 'DC sync IO error',
    0x0034: 'DC sync timeout error',
    0x0035: 'DC invalid sync cycle time',
    0x0036: 'DC invalid SYNC0 cycle time',
    0x0037: 'DC invalid SYNC1 cycle time',
}


def al_status_text(code: int) -> str:
    """Return the ETG.1000.6 meaning of an AL status code."""
    if code in AL_STATUS_TEXT:
        return AL_STATUS_TEXT[code]
    if 0x8000 <= code <= 0xFFFF:
        return f'vendor specific AL status code 0x{code:04X}'
    return f'unknown AL status code 0x{code:04X}'


def al_state_name(value: int) -> str:
    """Describe an AL status register value, e.g. ``'SAFE_OP+ERROR'``."""
    try:
        name = ALState(value & AL_STATE_MASK).name
    except ValueError:
        name = f'0x{value & AL_STATE_MASK:X}'
    return name + ('+ERROR' if value & AL_ERROR_FLAG else '')


#: SDO abort codes (CiA 301 v4.2 table 22; ETG.1000.6 table 43 adds 0x0601000x)
SDO_ABORT_TEXT: dict[int, str] = {
    0x05030000: 'Toggle bit not alternated',
    0x05040000: 'SDO protocol timed out',
    0x05040001: 'Client/server command specifier not valid or unknown',
    0x05040005: 'Out of memory',
    0x06010000: 'Unsupported access to an object',
    0x06010001: 'Attempt to read a write only object',
    0x06010002: 'Attempt to write a read only object',
    0x06010003: 'Subindex cannot be written, SI0 must be 0 for write access',
    0x06010004: 'SDO complete access not supported for objects of variable length',
    0x06010005: 'Object length exceeds mailbox size',
    0x06010006: 'Object mapped to RxPDO, SDO download blocked',
    0x06020000: 'Object does not exist in the object dictionary',
    0x06040041: 'Object cannot be mapped to the PDO',
    0x06040042: 'The number and length of the objects to be mapped would exceed PDO length',
    0x06040043: 'General parameter incompatibility reason',
    0x06040047: 'General internal incompatibility in the device',
    0x06060000: 'Access failed due to a hardware error',
    0x06070010: 'Data type does not match, length of service parameter does not match',
    0x06070012: 'Data type does not match, length of service parameter too high',
    0x06070013: 'Data type does not match, length of service parameter too low',
    0x06090011: 'Sub-index does not exist',
    0x06090030: 'Invalid value for parameter (download only)',
    0x06090031: 'Value of parameter written too high (download only)',
    0x06090032: 'Value of parameter written too low (download only)',
    0x06090036: 'Maximum value is less than minimum value',
    0x08000000: 'General error',
    0x08000020: 'Data cannot be transferred or stored to the application',
    0x08000021: 'Data cannot be transferred or stored to the application because of local '
                'control',
    0x08000022: 'Data cannot be transferred or stored to the application because of the '
                'present device state',
    0x08000023: 'Object dictionary dynamic generation fails or no object dictionary is present',
}


class SdoAbortCode(enum.IntEnum):
    """The abort codes the simulated slaves use by name (values from ``SDO_ABORT_TEXT``)."""

    TOGGLE_BIT_NOT_ALTERNATED = 0x05030000
    COMMAND_SPECIFIER_UNKNOWN = 0x05040001
    UNSUPPORTED_ACCESS = 0x06010000
    READ_WRITE_ONLY = 0x06010001
    WRITE_READ_ONLY = 0x06010002
    SUBINDEX_0_MUST_BE_0 = 0x06010003
    OBJECT_DOES_NOT_EXIST = 0x06020000
    NOT_MAPPABLE = 0x06040041
    PDO_LENGTH_EXCEEDED = 0x06040042
    PARAMETER_INCOMPATIBILITY = 0x06040043
    LENGTH_MISMATCH = 0x06070010
    LENGTH_TOO_HIGH = 0x06070012
    LENGTH_TOO_LOW = 0x06070013
    SUBINDEX_DOES_NOT_EXIST = 0x06090011
    VALUE_RANGE_EXCEEDED = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL_ERROR = 0x08000000
    DEVICE_STATE = 0x08000022


def sdo_abort_text(code: int) -> str:
    """Return the CiA 301 meaning of an SDO abort code."""
    return SDO_ABORT_TEXT.get(code, f'unknown SDO abort code 0x{code:08X}')


class MailboxType(enum.IntEnum):
    """Mailbox header type field (ETG.1000.6 table 29)."""

    ERROR = 0x00
    AOE = 0x01
    EOE = 0x02
    COE = 0x03
    FOE = 0x04
    SOE = 0x05
    VOE = 0x0F


class MailboxErrorCode(enum.IntEnum):
    """Detail codes of a mailbox error reply (ETG.1000.6 table 30)."""

    SYNTAX = 0x0001
    UNSUPPORTED_PROTOCOL = 0x0002
    INVALID_CHANNEL = 0x0003
    SERVICE_NOT_SUPPORTED = 0x0004
    INVALID_HEADER = 0x0005
    SIZE_TOO_SHORT = 0x0006
    NO_MORE_MEMORY = 0x0007
    INVALID_SIZE = 0x0008


class CoeService(enum.IntEnum):
    """CoE header service field (ETG.1000.6 table 38)."""

    EMERGENCY = 0x01
    SDO_REQUEST = 0x02
    SDO_RESPONSE = 0x03
    TXPDO = 0x04
    RXPDO = 0x05
    TXPDO_REMOTE_REQUEST = 0x06
    RXPDO_REMOTE_REQUEST = 0x07
    SDO_INFORMATION = 0x08


#: mailbox protocols announced in SII word 0x001C (ETG.1000.6 table 18)
MAILBOX_PROTOCOL_COE = 0x0004

#: CoE details byte of the SII general category (ETG.2010 table 8)
COE_DETAIL_SDO = 0x01
COE_DETAIL_SDO_INFO = 0x02
COE_DETAIL_PDO_ASSIGN = 0x04
COE_DETAIL_PDO_CONFIG = 0x08
COE_DETAIL_UPLOAD_AT_STARTUP = 0x10
COE_DETAIL_COMPLETE_ACCESS = 0x20


class Register(enum.IntEnum):
    """ESC registers (ETG.1000.4 section 6 / table 31 ff.; ESC datasheet section II)."""

    TYPE = 0x0000
    REVISION = 0x0001
    BUILD = 0x0002
    FMMU_COUNT = 0x0004
    SM_COUNT = 0x0005
    RAM_SIZE = 0x0006
    PORT_DESCRIPTOR = 0x0007
    FEATURES = 0x0008
    STATION_ADDRESS = 0x0010
    STATION_ALIAS = 0x0012
    DL_CONTROL = 0x0100
    DL_STATUS = 0x0110
    AL_CONTROL = 0x0120
    AL_STATUS = 0x0130
    AL_STATUS_CODE = 0x0134
    PDI_CONTROL = 0x0140
    ECAT_EVENT_MASK = 0x0200
    ECAT_EVENT_REQUEST = 0x0210
    RX_ERROR_COUNTER = 0x0300
    WATCHDOG_DIVIDER = 0x0400
    WATCHDOG_TIME_PDI = 0x0410
    WATCHDOG_TIME_PROCESS_DATA = 0x0420
    WATCHDOG_STATUS_PROCESS_DATA = 0x0440
    WATCHDOG_COUNTER_PROCESS_DATA = 0x0442
    WATCHDOG_COUNTER_PDI = 0x0443
    EEPROM_CONFIG = 0x0500
    EEPROM_PDI_ACCESS = 0x0501
    EEPROM_CONTROL = 0x0502
    EEPROM_ADDRESS = 0x0504
    EEPROM_DATA = 0x0508
    FMMU0 = 0x0600
    SM0 = 0x0800
    DC_RECEIVE_TIME_PORT0 = 0x0900
    DC_RECEIVE_TIME_PORT1 = 0x0904
    DC_RECEIVE_TIME_PORT2 = 0x0908
    DC_RECEIVE_TIME_PORT3 = 0x090C
    DC_SYSTEM_TIME = 0x0910
    DC_RECEIVE_TIME_PU = 0x0918
    DC_SYSTEM_TIME_OFFSET = 0x0920
    DC_SYSTEM_TIME_DELAY = 0x0928
    DC_SYSTEM_TIME_DIFFERENCE = 0x092C
    DC_SPEED_COUNTER_START = 0x0930
    DC_TIME_FILTER = 0x0934
    DC_CYCLIC_UNIT_CONTROL = 0x0980
    DC_SYNC_ACTIVATION = 0x0981
    DC_SYNC0_START_TIME = 0x0990
    DC_SYNC0_CYCLE_TIME = 0x09A0
    DC_SYNC1_CYCLE_TIME = 0x09A4


#: length of one FMMU / SyncManager register block (ETG.1000.4 6.6, 6.7)
FMMU_SIZE = 16
SM_SIZE = 8
