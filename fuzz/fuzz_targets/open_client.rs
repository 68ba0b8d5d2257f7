//! The server opening arbitrary datagrams claiming to come from a client. Nothing may
//! panic and, without the key, nothing may authenticate or move the replay window.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{ServerSession, SessionKeys};

fuzz_target!(|data: &[u8]| {
    let keys = SessionKeys { session_id: 0x0102_0304_0506_0708, client_to_server: [1; 32], server_to_client: [2; 32] };
    let mut session = ServerSession::new(&keys);
    let mut d = data.to_vec();
    assert!(session.open(&mut d).is_err());
    assert_eq!(session.opener.window().newest(), None);
});
