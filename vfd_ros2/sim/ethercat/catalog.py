"""Drive families for the simulated EtherCAT segment, as data, with their manual sources.

Line numbers ("L...") refer to the original manual text in ``shared/seeds``
(BONENG MH/MP: 000_c19f85fd6b43004e.txt; IMO HD2 cards: 004_2e8c796eaa0242ce.txt);
where a manual is silent the value is marked as assumed. What the driver also
relies on - identity, device name, PDO assignment, sync modes and cycles - is
read from the profiles' ``ethercat`` sections (one source of truth); the rest
(mailbox/SM addresses, ramps, vendor objects) is the simulator's own.
"""

from __future__ import annotations

from ...profiles import EthercatSpec, load_profile
from .drive import MODE_CSV, MODE_PV, MODE_VL, DriveSpec, ObjectSpec, PdoSpec
from .objects import Access, DataType

_u16, _u32, _i16, _i32 = DataType.UNSIGNED16, DataType.UNSIGNED32, DataType.INTEGER16, \
    DataType.INTEGER32
_rw, _ro = Access.RW, Access.RO


def _ethercat(profile: str) -> EthercatSpec:
    spec = load_profile(profile).ethercat
    if spec is None:
        raise ValueError(f'profile {profile} has no ethercat section')
    return spec


def _sync0(spec: EthercatSpec) -> tuple[int, ...] | None:
    return tuple(c * 1000 for c in spec.sync_cycles_us) if spec.dc else None


_MH = _ethercat('boneng_mh')
_HD2 = _ethercat('imo_hd2')

BONENG_MH_EC = DriveSpec(
    name=_MH.identity.device_name,                     # 0x1008, L3760
    # 0x1018:1/2 print 0 (L3763-3766): the real identity is only in the ESI file
    # Boneng_AD_EC.xml, which the manual does not reproduce (the profile leaves it open).
    vendor_id=_MH.identity.vendor_id or 0,
    product_code=_MH.identity.product_code or 0,
    revision=0x00000001,
    serial=0x00000001,
    device_type=0x00010192,                            # 0x1000, L3758
    # PDO table L3484-3490: 0x1600 custom (max 8), 0x1701 CoE_VL fixed, 0x1702 normal mode
    rx_pdos=(
        PdoSpec(0x1600, ((0x6040, 0, 16), (0x6042, 0, 16))),
        PdoSpec(0x1701, ((0x6040, 0, 16), (0x6042, 0, 16)), fixed=True),
        PdoSpec(0x1702, tuple((0x4000, n, 16) for n in range(1, 17)), fixed=True,
                max_entries=16),
    ),
    tx_pdos=(
        PdoSpec(0x1A00, ((0x6041, 0, 16), (0x6044, 0, 16))),
        PdoSpec(0x1B01, ((0x6041, 0, 16), (0x6044, 0, 16)), fixed=True),
        PdoSpec(0x1B02, tuple((0x4100, n, 16) for n in range(1, 17)), fixed=True,
                max_entries=16),
    ),
    # 0x1C12:1 / 0x1C13:1 are RO and print 1700h / 1B00h (L3805-3810; EN 1800h), which
    # name no PDO of L3484-3490: read as the CoE_VL pair 0x1701 / 0x1B01.
    rx_assign=_MH.rx_pdos,
    tx_assign=_MH.tx_pdos,
    assign_writable=False,
    modes=(MODE_VL,),                                   # CoE_VL = vl mode only (L3527-3531)
    default_mode=MODE_VL,
    mode_writable=False,                                # 0x6060 RO (OD table)
    rated_rpm=1500.0,
    max_rpm=1500.0,                                     # 0x6046:2 = 0x5DC (L3821-3824)
    accel_time_s=5.0,                                   # 0x6048 1500 rpm / 5 s (L3826-3828)
    decel_time_s=5.0,                                   # 0x6049
    quick_stop_time_s=5.0,                              # 0x604A
    quick_stop_option=1,                                # 0x605A default 1
    reverse_bit=11,                                     # 0x87F = reverse run (L3558-3561)
    vl_ramp_bits=True,                                  # bits 4-6 RFG sources (L3533-3556)
    # mailbox and SM addresses are not in the manual (ESI only): assumed defaults
    mailbox=(0x1000, 128, 0x1080, 128),
    process_data_starts=(0x1100, 0x1180),
    sync0_cycles_ns=_sync0(_MH),                        # DC not described: free run only
    free_run=_MH.free_run,
    objects=(
        ObjectSpec(0x4000, 0, 'R-PZD: entries', DataType.UNSIGNED8, _ro, 16),
        *(ObjectSpec(0x4000, n, f'R-PZD{n}', _u16, _rw, 0, True) for n in range(1, 17)),
        ObjectSpec(0x4100, 0, 'T-PZD: entries', DataType.UNSIGNED8, _ro, 16),
        *(ObjectSpec(0x4100, n, f'T-PZD{n}', _u16, _ro, 0, True) for n in range(1, 17)),
        ObjectSpec(0x605B, 0, 'Shutdown option code', _i16, _rw, 1),
    ),
    sources=('BONENG MH/MP manual ch. 8 (EtherCAT): L3427-3843; English L7278-7687',),
)

IMO_HD2_EC_TX508 = DriveSpec(
    name=_HD2.identity.device_name,                     # 1008h, L2366
    vendor_id=_HD2.identity.vendor_id or 0,             # 1018h:1, L2371
    product_code=_HD2.identity.product_code or 0,       # 1018h:2, L2372
    revision=0x00000001,                                # 1018h:3
    serial=0x00000001,                                  # 1018h:4
    device_type=0x00000192,                             # 1000h, L2364
    # default mapping, section 4.4.4 (L1641-1646) and Appendix A (L2375-2435); TxPDO
    # entry 7 is 0x603F in 4.4.4 and 0x60B9 in Appendix A (L2412): 0x603F is used
    rx_pdos=(
        PdoSpec(0x1600, ((0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6071, 0, 16),
                         (0x6072, 0, 16), (0x6060, 0, 8), (0x6081, 0, 32), (0x60B8, 0, 16))),
        *(PdoSpec(index, ((0x6040, 0, 16), (0x607A, 0, 32))) for index in (0x1601, 0x1602,
                                                                           0x1603)),
    ),
    tx_pdos=(
        PdoSpec(0x1A00, ((0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6077, 0, 16),
                         (0x60F4, 0, 32), (0x6061, 0, 8), (0x603F, 0, 16), (0x60BA, 0, 32))),
        *(PdoSpec(index, ((0x6041, 0, 16), (0x6064, 0, 32))) for index in (0x1A01, 0x1A02,
                                                                           0x1A03)),
    ),
    rx_assign=_HD2.rx_pdos,                             # 1C12h:1, L2438 (RW)
    tx_assign=_HD2.tx_pdos,                             # 1C13h:1 (RW)
    assign_writable=True,
    # 6502h = 0x3A5: pp, pv, hm, csp, csv, cst (L2541); the simulation moves in pv/csv
    modes=(1, MODE_PV, 6, 8, MODE_CSV, 10),
    default_mode=0,                                     # 6060h default 0 (Appendix A)
    mode_writable=True,
    rated_rpm=1500.0,                                   # not in the card manual: assumed
    max_rpm=3000.0,                                     # assumed
    accel_time_s=2.0,                                   # assumed (ramps are VFD parameters)
    decel_time_s=2.0,
    quick_stop_time_s=1.0,
    mailbox=(0x1000, 512, 0x1400, 512),                 # Table 4-4, L1589-1599
    process_data_starts=(0x1800, 0x1C00),
    # free run and DC SYNC0 (L1652-1654) at 250 us, 500 us, 1 ms, 2 ms (Table 4-1, L1517)
    sync0_cycles_ns=_sync0(_HD2),
    free_run=_HD2.free_run,
    # function-code access over 2000h-2003h (4.6, L1813-1824): P00.01 = 2, P00.02 = 3
    # (L1766), P00.10 = 50.00 Hz keypad frequency (L1822), P16.18 = 0.5 s (L2682)
    function_codes=((0x0001, 2), (0x0002, 3), (0x000A, 5000), (0x1012, 5)),
    objects=(
        ObjectSpec(0x607A, 0, 'Target position', _i32, _rw, 0, True),
        ObjectSpec(0x6071, 0, 'Target torque', _i16, _rw, 0, True),
        ObjectSpec(0x6072, 0, 'Max. torque', _u16, _rw, 0, True),
        ObjectSpec(0x6081, 0, 'Profile velocity', _u32, _rw, 0, True),
        ObjectSpec(0x60B8, 0, 'Touch probe function', _u16, _rw, 0, True),
        ObjectSpec(0x60B9, 0, 'Touch probe status', _u16, _ro, 0, True),
        ObjectSpec(0x60BA, 0, 'Touch probe position 1 positive', _i32, _ro, 0, True),
        ObjectSpec(0x60F4, 0, 'Following error actual value', _i32, _ro, 0, True),
    ),
    sources=('IMO HD2 communication card manual ch. 4 (EC-TX508): L1500-1831; '
             'Appendix A L2360-2541',),
)

CATALOG: dict[str, DriveSpec] = {
    'boneng_mh_ec': BONENG_MH_EC,
    'imo_hd2_ec': IMO_HD2_EC_TX508,
}
