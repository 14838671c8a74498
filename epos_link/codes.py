"""Wire constants of MAXON SERIAL V2 and the communication error codes.

Sources: EPOS4 Communication Guide (rel7290) chapter 2.1 (op codes), 2.2.2
(frame fields), chapter 6 Table 6-21 (error codes, CiA 301 plus maxon's
0x0F00xxxx codes).
"""
from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

DLE = 0x90  # Data Link Escape, first sync byte (guide 2.2.2)
STX = 0x02  # Start of Text, second sync byte
MAX_LEN_WORDS = 143  # Len is "the number of words in the data fields [0...143]"
MAX_SEGMENT = 255  # "Length (max. 255 bytes)" of a segment; the frame limit caps it lower


class OpCode(IntEnum):
    """Op codes of the USB/RS232 command reference (guide 2.1)."""

    ANSWER = 0x00
    READ_OBJECT = 0x60
    SEGMENT_READ = 0x62
    WRITE_OBJECT = 0x68
    INITIATE_SEGMENTED_WRITE = 0x69
    SEGMENT_WRITE = 0x6A
    SEND_NMT_SERVICE = 0x70
    INITIATE_SEGMENTED_READ = 0x81


OPCODE_NAMES = {
    OpCode.ANSWER: "Answer",
    OpCode.READ_OBJECT: "ReadObject",
    OpCode.SEGMENT_READ: "SegmentRead",
    OpCode.WRITE_OBJECT: "WriteObject",
    OpCode.INITIATE_SEGMENTED_WRITE: "InitiateSegmentedWrite",
    OpCode.SEGMENT_WRITE: "SegmentWrite",
    OpCode.SEND_NMT_SERVICE: "SendNMTService",
    OpCode.INITIATE_SEGMENTED_READ: "InitiateSegmentedRead",
}


def opcode_name(opcode: int) -> str:
    try:
        return OPCODE_NAMES[OpCode(opcode)]
    except ValueError:
        return f"Unknown(0x{opcode:02X})"


class NmtCommand(IntEnum):
    """NMT command specifiers (guide Table 3-14), carried by SendNMTService."""

    START_REMOTE_NODE = 0x01
    STOP_REMOTE_NODE = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class ErrorInfo(NamedTuple):
    name: str
    cause: str


class ErrorCode(IntEnum):
    """Communication error codes, guide Table 6-21, complete."""

    NO_ABORT = 0x00000000
    TOGGLE_ERROR = 0x05030000
    COMMAND_UNKNOWN = 0x05040001
    CRC_ERROR = 0x05040004
    ACCESS_ERROR = 0x06010000
    WRITE_ONLY_ERROR = 0x06010001
    READ_ONLY_ERROR = 0x06010002
    OBJECT_DOES_NOT_EXIST = 0x06020000
    PDO_MAPPING_ERROR = 0x06040041
    PDO_LENGTH_ERROR = 0x06040042
    GENERAL_PARAMETER_ERROR = 0x06040043
    GENERAL_INTERNAL_INCOMPATIBILITY = 0x06040047
    HARDWARE_ERROR = 0x06060000
    SERVICE_PARAMETER_ERROR = 0x06070010
    SUBINDEX_ERROR = 0x06090011
    VALUE_RANGE_ERROR = 0x06090030
    GENERAL_ERROR = 0x08000000
    TRANSFER_OR_STORE_ERROR = 0x08000020
    WRONG_DEVICE_STATE = 0x08000022
    PASSWORD_ERROR = 0x0F00FFBE
    ILLEGAL_COMMAND = 0x0F00FFBF
    WRONG_NMT_STATE = 0x0F00FFC0


# Names and causes as printed in Table 6-21.
ERROR_TABLE: dict[int, ErrorInfo] = {
    0x00000000: ErrorInfo("No abort", "Communication successful"),
    0x05030000: ErrorInfo("Toggle error", "Toggle bit not alternated"),
    0x05040001: ErrorInfo("Command unknown", "Command specifier unknown"),
    0x05040004: ErrorInfo("CRC error", "CRC check failed"),
    0x06010000: ErrorInfo("Access error", "Unsupported access to an object"),
    0x06010001: ErrorInfo("Write only error", "Read command to a write only object"),
    0x06010002: ErrorInfo("Read only error", "Write command to a read only object"),
    0x06020000: ErrorInfo("Object does not exist error",
                          "Last read or write command had wrong object index or subindex"),
    0x06040041: ErrorInfo("PDO mapping error", "Object is not mappable to the PDO"),
    0x06040042: ErrorInfo("PDO length error",
                          "Number and length of objects to be mapped would exceed PDO length"),
    0x06040043: ErrorInfo("General parameter error", "General parameter incompatibility"),
    0x06040047: ErrorInfo("General internal incompatibility error",
                          "General internal incompatibility in device"),
    0x06060000: ErrorInfo("Hardware error", "Access failed due to hardware error"),
    0x06070010: ErrorInfo("Service parameter error",
                          "Data type does not match, length or service parameter do not match"),
    0x06090011: ErrorInfo("Subindex error", "Last read or write command had wrong object subindex"),
    0x06090030: ErrorInfo("Value range error", "Value range of parameter exceeded"),
    0x08000000: ErrorInfo("General error", "General error"),
    0x08000020: ErrorInfo("Transfer or store error", "Data cannot be transferred or stored"),
    0x08000022: ErrorInfo("Wrong device state error",
                          "Data cannot be transferred or stored to application because of "
                          "present device state"),
    0x0F00FFBE: ErrorInfo("Password error", "Password is incorrect"),
    0x0F00FFBF: ErrorInfo("Illegal command error", "Command code is illegal (does not exist)"),
    0x0F00FFC0: ErrorInfo("Wrong NMT state error", "Device is in wrong NMT state"),
}

# CiA 301 codes that a gateway may relay from a remote node's SDO server but
# that Table 6-21 does not list. Kept apart so the guide's table stays exact.
CIA301_EXTRA: dict[int, ErrorInfo] = {
    0x05040000: ErrorInfo("SDO protocol timed out", "SDO protocol timed out"),
    0x05040002: ErrorInfo("Invalid block size", "Invalid block size (block mode only)"),
    0x05040005: ErrorInfo("Out of memory", "Out of memory"),
    0x06070012: ErrorInfo("Data type does not match, length too high",
                          "Data type does not match, length of service parameter too high"),
    0x06070013: ErrorInfo("Data type does not match, length too low",
                          "Data type does not match, length of service parameter too low"),
    0x06090031: ErrorInfo("Value too high", "Value of parameter written too high"),
    0x06090032: ErrorInfo("Value too low", "Value of parameter written too low"),
    0x08000021: ErrorInfo("Local control", "Data cannot be transferred or stored because of local control"),
}


def error_info(code: int) -> ErrorInfo | None:
    return ERROR_TABLE.get(code) or CIA301_EXTRA.get(code)


def describe_error(code: int) -> str:
    """The name of an error code, or the code in hex when it is unknown."""
    info = error_info(code)
    return info.name if info else f"Unknown error 0x{code:08X}"


# Device error codes (603Fh, 1003h) of the EPOS4, with the names of the EPOS4
# Firmware Specification's error table (section 7.2), as transcribed in public
# EPOS4 code. Not the communication errors above: these say why a drive is in
# FAULT. The simulator's injectable faults use 0x8611 and 0x8A80..0x8A88.
DEVICE_ERRORS: dict[int, str] = {
    0x0000: "No error",
    0x1000: "Generic error",
    0x1090: "Firmware incompatibility error",
    0x2310: "Overcurrent error",
    0x2320: "Power stage protection error",
    0x3210: "Overvoltage error",
    0x3220: "Undervoltage error",
    0x4210: "Thermal overload error",
    0x4380: "Thermal motor overload error",
    0x5113: "Logic supply voltage too low error",
    0x5280: "Hardware defect error",
    0x5281: "Hardware incompatibility error",
    0x6080: "Sign of life error",
    0x6081: "Extension 1 watchdog error",
    0x6320: "Software parameter error",
    0x6380: "Persistent parameter corrupt error",
    0x7320: "Position sensor error",
    0x7380: "Position sensor breach error",
    0x7381: "Position sensor resolution error",
    0x7382: "Position sensor index error",
    0x7388: "Hall sensor error",
    0x7389: "Hall sensor not found error",
    0x738A: "Hall angle detection error",
    0x738C: "SSI sensor error",
    0x7390: "Missing main sensor error",
    0x7391: "Missing commutation sensor error",
    0x7392: "Main sensor direction error",
    0x8110: "CAN overrun error (object lost)",
    0x8111: "CAN overrun error",
    0x8120: "CAN passive mode error",
    0x8130: "CAN heartbeat error",
    0x8150: "CAN PDO COB-ID collision",
    0x81FD: "CAN bus turned off",
    0x81FE: "CAN Rx queue overflow",
    0x81FF: "CAN Tx queue overflow",
    0x8210: "CAN PDO length error",
    0x8250: "RPDO timeout",
    0x8611: "Following error",
    0x8A80: "Negative limit switch error",
    0x8A81: "Positive limit switch error",
    0x8A82: "Software position limit error",
    0x8A88: "STO error",
    0xFF01: "System overloaded error",
    0xFF02: "Watchdog error",
    0xFF0B: "System peak overloaded error",
    0xFF10: "Controller gain error",
}


def describe_device_error(code: int) -> str:
    """The EPOS4 name of a 603Fh error code, or the code in hex when it is unknown."""
    return DEVICE_ERRORS.get(code, f"Unknown device error 0x{code:04X}")
