fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).unwrap());
    for p in ["rig", "emulator", "controller"] {
        let mut t = fastemu::records::tail::PartTail::new(dir.clone(), p);
        let mut topics = std::collections::BTreeMap::new();
        let n = t.poll(|m| *topics.entry(m.topic).or_insert(0) += 1);
        println!("{p}: {n} {topics:?} err {:?}", t.error);
    }
}
