//! The zones' fabric messages (`myriad_zone::wire`). The input is signed with the
//! fuzzer's key first, so that it passes the tag check and reaches the parser: decoding
//! must never panic, and whatever decodes must re-encode to the same bytes (one encoding
//! per message). The input as it came, unsigned, must never decode.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_zone::wire::{ClusterKey, VERSION, decode, encode, sign};

fuzz_target!(|data: &[u8]| {
    let key = ClusterKey::new(b"the fuzzer's cluster key, 32 b!!").unwrap();
    assert!(decode(&key, data).is_err(), "nothing unsigned decodes");
    // Magic and version first, so that the fuzzer spends its time behind them.
    let mut body = vec![b'M', b'Z', VERSION];
    body.extend_from_slice(data);
    let signed = sign(&key, &body);
    if let Ok(m) = decode(&key, &signed) {
        assert_eq!(encode(&key, &m).unwrap(), signed);
    }
});
