use super::*;
use crate::layout::ZoneId;
use crate::nats::zone_subject;

#[test]
fn patterns_match_as_nats_matches_them() {
    assert!(subject_matches("a.*.c", "a.b.c"));
    assert!(!subject_matches("a.*.c", "a.b.c.d"));
    assert!(!subject_matches("a.*", "a"));
    assert!(subject_matches("a.>", "a.b.c"));
    assert!(!subject_matches("a.>", "a"));
    assert!(subject_matches("$O.myriad-c.>", "$O.myriad-c.C.xyz"));
    assert!(!subject_matches("a.b", "a.bb"));
}

/// The roles of the tables below: zones 0 and 1, the gateways, the supervisor.
const ROLES: [Role; 4] = [Role::Zone(ZoneId(0)), Role::Zone(ZoneId(1)), Role::Gateway, Role::Supervisor];

/// The subject table of docs/zones.md, as the permissions must grant it: every
/// (subject, role) pair here is checked, in both directions.
#[test]
fn each_role_publishes_exactly_its_subjects() {
    let c = "c";
    let zone0 = zone_subject(c, ZoneId(0));
    let zone7 = zone_subject(c, ZoneId(7));
    let table: &[(&str, [bool; 4])] = &[
        // subject: may (zone 0, zone 1, gateway, supervisor) publish it?
        (&zone0, [true, true, false, false]),
        (&zone7, [true, true, false, false]),
        ("myriad.c.states", [true, true, false, false]),
        // States by interest: views from zones, subscriptions from gateways.
        ("myriad.c.view.0", [true, true, false, false]),
        ("myriad.c.view.63", [true, true, false, false]),
        ("myriad.c.view", [false; 4]),
        ("myriad.c.subscriptions", [false, false, true, false]),
        ("myriad.d.subscriptions", [false; 4]),
        // Each zone its own heartbeat only.
        ("myriad.c.heartbeat.0", [true, false, false, false]),
        ("myriad.c.heartbeat.1", [false, true, false, false]),
        ("myriad.c.heartbeat", [false; 4]),
        ("myriad.c.control", [false, false, false, true]),
        // Cut moves: the supervisor's alone.
        ("myriad.c.cuts", [false, false, false, true]),
        ("myriad.d.cuts", [false; 4]),
        ("myriad.c.intents", [false, false, true, false]),
        ("myriad.c.sessions", [false, false, true, false]),
        ("$O.myriad-c.C.abc", [true, true, false, true]),
        ("$O.myriad-c.M.ei10LXQzMA==", [true, true, false, true]),
        ("$JS.API.STREAM.CREATE.OBJ_myriad-c", [true, true, false, true]),
        ("$JS.API.STREAM.DELETE.OBJ_myriad-c", [false, false, false, true]),
        // Another cluster's subjects and bucket, and the JetStream API at large: nobody.
        ("myriad.d.zone.0", [false; 4]),
        ("myriad.d.heartbeat.0", [false; 4]),
        ("myriad.c.zone.0.x", [false; 4]),
        ("$O.myriad-d.C.abc", [false; 4]),
        ("$JS.API.STREAM.CREATE.OBJ_myriad-d", [false; 4]),
        ("$JS.API.STREAM.DELETE.OBJ_myriad-d", [false; 4]),
        ("$JS.API.STREAM.LIST", [false; 4]),
        ("$JS.API.ACCOUNT.INFO", [false; 4]),
        ("_INBOX.abc", [false; 4]),
    ];
    for (subject, may) in table {
        for (role, may) in ROLES.into_iter().zip(may) {
            assert_eq!(permissions(c, role).may_publish(subject), *may, "{role:?} publishing {subject}");
        }
    }
}

#[test]
fn each_role_hears_only_what_is_addressed_to_it() {
    let c = "c";
    let table: &[(&str, [bool; 4])] = &[
        ("myriad.c.zone.3", [true, true, false, false]),
        // Every zone hears the supervisor's orders and cut moves; gateways hear them
        // too, for their operators' map of the cuts (they route nothing by them).
        ("myriad.c.control", [true, true, true, false]),
        ("myriad.c.cuts", [true, true, true, false]),
        ("myriad.d.cuts", [false; 4]),
        ("myriad.c.intents", [true, true, false, false]),
        ("myriad.c.heartbeat.0", [false, false, false, true]),
        ("myriad.c.heartbeat.*", [false, false, false, true]),
        ("myriad.c.states", [false, false, true, false]),
        ("myriad.c.sessions", [false, false, true, false]),
        ("myriad.c.subscriptions", [true, true, false, false]),
        ("myriad.c.view.1", [false, false, true, false]),
        ("myriad.c.view.*", [false, false, true, false]),
        ("myriad.d.view.1", [false; 4]),
        ("_INBOX.abc.def", [true, true, false, true]),
        ("$O.myriad-c.C.abc", [false; 4]),
        ("myriad.d.zone.3", [false; 4]),
    ];
    for (subject, may) in table {
        for (role, may) in ROLES.into_iter().zip(may) {
            assert_eq!(permissions(c, role).may_subscribe(subject), *may, "{role:?} subscribing to {subject}");
        }
    }
}

#[test]
fn the_configuration_lists_every_role_with_its_permissions() {
    let creds = new_credentials("w1", 2).unwrap();
    assert_eq!(
        creds.iter().map(|c| c.user.as_str()).collect::<Vec<_>>(),
        ["myriad-w1-zone-0", "myriad-w1-zone-1", "myriad-w1-gateway", "myriad-w1-supervisor"]
    );
    assert_ne!(creds[0].password, creds[1].password, "a password per role");
    assert!(creds[0].password.len() >= 48, "192 bits in hex");
    let text = render_server_config("w1", &creds, "127.0.0.1:4333", Path::new("/tmp/js")).unwrap();
    assert!(text.starts_with("listen: \"127.0.0.1:4333\"\njetstream {\n  store_dir: \"/tmp/js\"\n}\n"), "{text}");
    for c in &creds {
        assert!(text.contains(&format!("user: \"{}\"\n      password: \"{}\"", c.user, c.password)), "{text}");
        let p = permissions("w1", c.role);
        assert!(text.contains(&format!("publish: {{ allow: [{}] }}", quoted_list(&p.publish))));
        assert!(text.contains(&format!("subscribe: {{ allow: [{}] }}", quoted_list(&p.subscribe))));
    }
    assert!(!format!("{creds:?}").contains(&creds[0].password), "Debug never shows a password");
    assert!(render_authorization("a.b", &creds).is_err(), "a cluster name is one token");
    let mut odd = creds.clone();
    odd[1].password = "pa\"ss".into();
    assert!(render_authorization("w1", &odd).is_err(), "nothing that needs quoting reaches the file");
}

#[test]
fn credentials_come_from_variables_or_a_file_never_half() {
    let vars = |pairs: &'static [(&'static str, &'static str)]| {
        move |k: &str| pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| v.to_string())
    };
    assert_eq!(NatsAuth::from_lookup(vars(&[])).unwrap(), NatsAuth::default());
    let a = NatsAuth::from_lookup(vars(&[(USER_ENV, "u"), (PASSWORD_ENV, "p"), (CA_ENV, "/ca.pem")])).unwrap();
    assert_eq!(a, NatsAuth::user("u", "p").with_ca("/ca.pem".into()));
    assert_eq!(a.env(), [(USER_ENV, "u".into()), (PASSWORD_ENV, "p".into()), (CA_ENV, "/ca.pem".into())]);
    assert!(!format!("{a:?}").contains("\"p\""), "Debug never shows the password");
    for bad in [
        &[(USER_ENV, "u")][..],
        &[(PASSWORD_ENV, "p")],
        &[(CREDS_ENV, "/x"), (USER_ENV, "u")],
        &[(CLIENT_CERT_ENV, "/c.pem")],
        &[(CREDS_ENV, "/nonexistent/myriad.creds")],
    ] {
        let pairs: &'static [(&'static str, &'static str)] = bad;
        assert!(NatsAuth::from_lookup(vars(pairs)).is_err(), "{bad:?}");
    }
    let dir = std::env::temp_dir().join(format!("myriad-creds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("zone.creds");
    let creds = &new_credentials("c", 1).unwrap()[0];
    write_private(&file, &creds.creds_file()).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(std::fs::metadata(&file).unwrap().permissions().mode() & 0o777, 0o600);
    }
    let path = file.display().to_string();
    let from_file = NatsAuth::from_lookup(|k| (k == CREDS_ENV).then(|| path.clone())).unwrap();
    assert_eq!(from_file, creds.auth());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_credentials_file_has_one_user_and_one_password() {
    assert_eq!(
        parse_creds("# zone\nMYRIAD_NATS_USER=u\n\nMYRIAD_NATS_PASSWORD = p \n"),
        Err("line 4: expected one MYRIAD_NATS_USER=... and one MYRIAD_NATS_PASSWORD=...".into()),
        "no spaces around the ="
    );
    assert_eq!(parse_creds("MYRIAD_NATS_USER=u\nMYRIAD_NATS_PASSWORD=p w\n"), Ok(("u".into(), "p w".into())));
    assert!(parse_creds("MYRIAD_NATS_USER=u\n").is_err());
    assert!(parse_creds("MYRIAD_NATS_USER=u\nMYRIAD_NATS_USER=v\nMYRIAD_NATS_PASSWORD=p\n").is_err());
    assert!(parse_creds("MYRIAD_NATS_USER=\nMYRIAD_NATS_PASSWORD=p\n").is_err());
    assert!(parse_creds("token=x\n").is_err());
}
