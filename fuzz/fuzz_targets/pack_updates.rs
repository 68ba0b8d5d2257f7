//! The update packer on arbitrary records: every datagram must fit the size limit,
//! decode, and together give back exactly the packed prefix of the input.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{
    DatagramBatch, HEADER_LEN, MAX_DATAGRAM, ShapeKind, PacketKind, QuantPos, ServerMessage, StateRecord, TAG_LEN,
    UpdateHeader, pack_updates,
};

fn i32_at(b: &[u8]) -> i32 {
    i32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

fuzz_target!(|data: &[u8]| {
    let [max, tick, ox0, ox1, ox2, ox3, rest @ ..] = data else { return };
    let header = UpdateHeader {
        tick: u64::from(*tick),
        dilation_permille: 1000,
        origin: QuantPos::new(i32_at(&[*ox0, *ox1, *ox2, *ox3]), i32_at(&[*ox3, *ox2, *ox1, *ox0]).wrapping_neg(), 0),
    };
    // 21 input bytes per record: id, kind, x, y, z.
    let records: Vec<StateRecord> = rest
        .chunks_exact(21)
        .map(|c| StateRecord {
            id: u64::from_le_bytes(c[0..8].try_into().expect("8 bytes")),
            kind: match c[8] % 3 {
                0 => ShapeKind::Sphere,
                1 => ShapeKind::Box,
                _ => ShapeKind::Capsule,
            },
            pos: QuantPos::new(i32_at(&c[9..13]), i32_at(&c[13..17]), i32_at(&c[17..21])),
        })
        .collect();
    let max = usize::from(*max % 8);
    let mut batch = DatagramBatch::new();
    let packed = pack_updates(&header, &records, max, &mut batch);
    assert!(batch.len() <= max);
    assert!(packed == records.len() || batch.len() == max);
    let mut got = Vec::new();
    for d in batch.iter() {
        assert!(d.len() <= MAX_DATAGRAM);
        assert_eq!(d[1], PacketKind::StateUpdate as u8);
        let body = &d[HEADER_LEN..d.len() - TAG_LEN];
        match ServerMessage::decode_body(PacketKind::StateUpdate, body) {
            Ok(ServerMessage::StateUpdate(u)) => {
                assert_eq!(u.header, header);
                got.extend(u.records);
            }
            other => panic!("packer produced an undecodable datagram: {other:?}"),
        }
    }
    assert_eq!(&got[..], &records[..packed]);
});
