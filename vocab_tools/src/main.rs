//! vocab-tools: descriptor extraction, HBST construction and place-recognition evaluation.
//! The subcommands arrive with the loop-closing issue; until then this binary only says so.

fn main() {
    eprintln!("vocab-tools: no subcommands yet (they come with the loop-closing work)");
    std::process::exit(2);
}
