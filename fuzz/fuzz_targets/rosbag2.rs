//! rosbag2 bags through the replay source's readers: the first byte picks a sqlite3 database
//! (opened read-only, every topic's messages walked, as the replay does) or a `metadata.yaml`.
#![no_main]

use gdvae_node::sources::rosbag2::{parse_metadata, Sqlite3Bag};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else { return };
    if kind % 2 == 1 {
        let _ = parse_metadata(&String::from_utf8_lossy(body), std::path::Path::new("/nonexistent-bag"));
        return;
    }
    let path = std::env::temp_dir().join(format!("gdvae-fuzz-{}.db3", std::process::id()));
    if std::fs::write(&path, body).is_err() {
        return;
    }
    let Ok(bag) = Sqlite3Bag::open(&path) else { return };
    let Ok(topics) = bag.topics() else { return };
    let names: Vec<&str> = topics.iter().map(|(name, _)| name.as_str()).collect();
    let mut bytes = 0usize;
    let _ = bag.for_each(&names, |message| {
        bytes += message.data.len();
        true
    });
});
