"""PDO COB-ID writes (CiA 301 §7.5.2.35): only what the PDO needs, bit 30 (RTR not allowed) kept as the drive has it."""

from stagectl.drivers.cia402 import PDO_DISABLED, PDO_NO_RTR, cob_id_writes


def test_a_pdo_already_on_our_cob_id_with_bit_30_is_not_written_again():
    """Many drives hold bit 30 at 1: a PDO already on our COB-ID needs the invalidation only (valid) or no write
    at all (invalid); a second write of the same value is a needless SDO (and an abort on a drive whose
    COB-ID bits 0-29 are read-only)."""
    cob = 0x181
    writes, valid = cob_id_writes(PDO_NO_RTR | cob, cob)
    assert writes == [(PDO_DISABLED | PDO_NO_RTR | cob, "COB-ID (disable)")] and valid == PDO_NO_RTR | cob
    writes, valid = cob_id_writes(PDO_DISABLED | PDO_NO_RTR | cob, cob)
    assert writes == [] and valid == PDO_NO_RTR | cob


def test_a_pdo_on_another_cob_id_is_invalidated_then_moved():
    writes, valid = cob_id_writes(PDO_NO_RTR | 0x182, 0x181)
    assert writes == [(PDO_DISABLED | PDO_NO_RTR | 0x182, "COB-ID (disable)"),
                      (PDO_DISABLED | PDO_NO_RTR | 0x181, "COB-ID (set while disabled)")]
    assert valid == PDO_NO_RTR | 0x181
    writes, valid = cob_id_writes(0x181, 0x181)  # bit 30 clear: one write, bit 30 stays clear
    assert writes == [(PDO_DISABLED | 0x181, "COB-ID (disable)")] and valid == 0x181
