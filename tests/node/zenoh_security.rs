//! Who can reach the node: its `[zenoh]` settings over a zenoh configuration file, and real
//! sessions on loopback behind a router with mutual TLS, user/password authentication and access
//! control, with certificates made here.

use std::path::Path;
use std::time::Duration;

use gdvae_node::zenoh_session::{open_session, open_to_the_network, plan, session_config_from, ZenohSettings};
use zenoh::Wait;

use crate::helpers::free_endpoint;

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

#[test]
fn the_toml_keys_that_are_set_apply_on_top_of_the_zenoh_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(
        dir.path(),
        "robot.json5",
        r#"{ mode: "client", connect: { endpoints: ["tls/base:7447"] }, listen: { endpoints: ["tls/0.0.0.0:7448"] } }"#,
    );
    let file = Path::new(&file);
    let from_file = plan(&session_config_from(&ZenohSettings::default(), Some(file)).unwrap());
    assert_eq!(from_file.mode, "client");
    assert_eq!(from_file.connect, vec!["tls/base:7447"]);
    assert_eq!(from_file.listen, vec!["tls/0.0.0.0:7448"]);
    let over = ZenohSettings {
        listen: Some(vec!["tcp/127.0.0.1:7449".into()]),
        ..Default::default()
    };
    let merged = plan(&session_config_from(&over, Some(file)).unwrap());
    assert_eq!(
        (merged.mode.as_str(), merged.connect.clone()),
        ("client", vec!["tls/base:7447".to_string()])
    );
    assert_eq!(merged.listen, vec!["tcp/127.0.0.1:7449"]);
    // Without a file: an embedded peer, as before files existed, which zenoh has listen on a
    // random port of every interface: reachable from the network, and flagged as such.
    let bare = plan(&session_config_from(&ZenohSettings::default(), None).unwrap());
    assert_eq!((bare.mode.as_str(), bare.connect.len()), ("peer", 0));
    assert_eq!(bare.listen, vec!["tcp/[::]:0"]);
    assert_eq!(open_to_the_network(&bare), bare.listen);
    // A file that is not there, or not JSON5, is named in the error.
    let missing = session_config_from(&ZenohSettings::default(), Some(&dir.path().join("none.json5"))).unwrap_err();
    assert!(missing.0.contains("none.json5"), "{}", missing.0);
    let broken = write(dir.path(), "broken.json5", "{ mode: ");
    let error = session_config_from(&ZenohSettings::default(), Some(Path::new(&broken))).unwrap_err();
    assert!(error.0.contains("broken.json5"), "{}", error.0);
    // Settings that name a file check it when the config is validated.
    let named = ZenohSettings {
        config: Some(dir.path().join("none.json5")),
        ..Default::default()
    };
    assert!(named.validate().unwrap_err().contains("none.json5"));
}

#[test]
fn the_shipped_zenoh_files_parse_and_say_what_they_do() {
    let folder = crate::helpers::repo().join("config/zenoh");
    let robot = plan(&session_config_from(&ZenohSettings::default(), Some(&folder.join("robot.json5"))).unwrap());
    assert_eq!(robot.mode, "client");
    assert_eq!(robot.connect, vec!["tls/base-station.local:7447"]);
    assert!(open_to_the_network(&robot).is_empty(), "{robot:?}");
    let base = plan(&zenoh::Config::from_file(folder.join("base-station.json5")).unwrap());
    assert_eq!(
        (base.mode.as_str(), base.listen.clone()),
        ("router", vec!["tls/0.0.0.0:7447".to_string()])
    );
    assert!(open_to_the_network(&base).is_empty());
}

#[test]
fn listening_beyond_loopback_without_tls_is_flagged() {
    let plan = gdvae_node::zenoh_session::SessionPlan {
        mode: "peer".into(),
        listen: [
            "tcp/0.0.0.0:7447",
            "tcp/192.168.1.5:7447",
            "udp/[::]:7447",
            "tcp/127.0.0.1:7447",
            "tcp/localhost:7447",
            "tcp/[::1]:7447",
            "tls/0.0.0.0:7448",
            "quic/0.0.0.0:7449",
        ]
        .map(String::from)
        .to_vec(),
        connect: vec![],
    };
    assert_eq!(
        open_to_the_network(&plan),
        vec!["tcp/0.0.0.0:7447", "tcp/192.168.1.5:7447", "udp/[::]:7447"]
    );
}

/// A CA, a router certificate for `localhost` and a client certificate for `robot1`, as PEM files.
fn certificates(dir: &Path) -> [String; 5] {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};
    let ca_key = KeyPair::generate().unwrap();
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name.push(DnType::CommonName, "test CA");
    let ca_pem = ca.self_signed(&ca_key).unwrap().pem();
    let issuer = Issuer::new(ca, ca_key);
    let leaf = |name: &str| {
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(vec![name.to_string()]).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        (params.signed_by(&key, &issuer).unwrap().pem(), key.serialize_pem())
    };
    let (router_pem, router_key) = leaf("localhost");
    let (robot_pem, robot_key) = leaf("robot1");
    [
        write(dir, "ca.pem", &ca_pem),
        write(dir, "router.pem", &router_pem),
        write(dir, "router.key", &router_key),
        write(dir, "robot1.pem", &robot_pem),
        write(dir, "robot1.key", &robot_key),
    ]
}

/// Whether a put on `key` from `session` reaches `received` within a second.
fn arrives(session: &zenoh::Session, key: &str, received: &crossbeam_channel::Receiver<String>) -> bool {
    while received.try_recv().is_ok() {}
    for _ in 0..10 {
        session.put(key, "state").wait().unwrap();
        if let Ok(got) = received.recv_timeout(Duration::from_millis(100)) {
            assert_eq!(got, key);
            return true;
        }
    }
    false
}

#[test]
fn behind_a_router_with_mutual_tls_and_passwords_only_the_robot_gets_in_and_only_to_its_keys() {
    let dir = tempfile::tempdir().unwrap();
    let [ca, router_pem, router_key, robot_pem, robot_key] = certificates(dir.path());
    let users = write(dir.path(), "users.txt", "robot1:secret\n");
    let port = free_endpoint().rsplit(':').next().unwrap().to_string();
    let router_config = format!(
        r#"{{
          mode: "router",
          listen: {{ endpoints: ["tls/127.0.0.1:{port}"] }},
          scouting: {{ multicast: {{ enabled: false }} }},
          transport: {{
            link: {{ tls: {{ root_ca_certificate: "{ca}", listen_private_key: "{router_key}",
                           listen_certificate: "{router_pem}", enable_mtls: true }} }},
            auth: {{ usrpwd: {{ dictionary_file: "{users}" }} }},
          }},
          access_control: {{
            enabled: true,
            default_permission: "allow",
            rules: [{{ id: "no-status-puts", messages: ["put"], flows: ["ingress"], permission: "deny",
                       key_exprs: ["gdvae/robot1/status"] }}],
            subjects: [{{ id: "anyone" }}],
            policies: [{{ rules: ["no-status-puts"], subjects: ["anyone"] }}],
          }},
        }}"#
    );
    let router = zenoh::open(zenoh::Config::from_json5(&router_config).unwrap())
        .wait()
        .unwrap();
    let (tx, received) = crossbeam_channel::unbounded();
    let _subscriber = router
        .declare_subscriber("gdvae/**")
        .callback(move |sample| {
            let _ = tx.send(sample.key_expr().to_string());
        })
        .wait()
        .unwrap();
    let client = |name: &str, certificate: bool, password: &str| {
        let tls = if certificate {
            format!(r#"enable_mtls: true, connect_private_key: "{robot_key}", connect_certificate: "{robot_pem}","#)
        } else {
            String::new()
        };
        write(
            dir.path(),
            name,
            &format!(
                r#"{{
                  mode: "client",
                  connect: {{ endpoints: ["tls/localhost:{port}"], timeout_ms: 2000 }},
                  scouting: {{ multicast: {{ enabled: false }} }},
                  transport: {{
                    link: {{ tls: {{ root_ca_certificate: "{ca}", {tls} }} }},
                    auth: {{ usrpwd: {{ user: "robot1", password: "{password}" }} }},
                  }},
                }}"#
            ),
        )
    };
    // The node, through its settings (the file, as `[zenoh] config` names it).
    let settings = ZenohSettings {
        config: Some(client("robot.json5", true, "secret").into()),
        ..Default::default()
    };
    settings.validate().unwrap();
    let node = open_session(&settings).expect("the robot's node connects");
    assert!(
        arrives(&node, "gdvae/robot1/walk/state", &received),
        "the robot's states reach the router"
    );
    assert!(
        !arrives(&node, "gdvae/robot1/status", &received),
        "the access control rule denies this key"
    );
    // Without a client certificate, or with a wrong password, or in plain TCP: no way in.
    let with_file = |name: &str, certificate: bool, password: &str| ZenohSettings {
        config: Some(client(name, certificate, password).into()),
        ..Default::default()
    };
    let rogues = [
        ("no certificate", with_file("no-cert.json5", false, "secret")),
        ("a wrong password", with_file("wrong.json5", true, "guess")),
        (
            "plain TCP",
            ZenohSettings {
                mode: Some("client".into()),
                connect: Some(vec![format!("tcp/127.0.0.1:{port}")]),
                multicast_scouting: Some(false),
                ..Default::default()
            },
        ),
    ];
    for (what, rogue) in rogues {
        if let Ok(session) = open_session(&rogue) {
            assert!(
                !arrives(&session, "gdvae/robot1/walk/state", &received),
                "{what} got in"
            );
        }
    }
}
