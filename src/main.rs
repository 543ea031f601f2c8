//! The `gonio` command line. Each subcommand lives in `src/cli/`.

use clap::Parser;

/// Stop glibc's malloc from returning every freed image to the kernel.
///
/// gonio allocates and frees a frame-sized buffer (0.8 MiB for a 256² RGB f32 image, 9 MiB
/// for a 1024 × 768 raw frame) thousands of times, on rayon's threads. With glibc's defaults
/// each such buffer is either mmapped and unmapped (above the dynamic mmap threshold) or
/// trimmed from a thread's arena when freed, so every new image page-faults its memory in
/// again and every unmap stops both cores for a TLB shoot-down: `gonio sim btf` (6561 truth
/// images of 256²) took 33.5 s on two cores, slower than the 27.4 s of one thread. With
/// buffers up to 32 MiB served from the heap and up to 128 MiB of freed memory kept, the
/// same run takes 11–14 s (measured with `MALLOC_MMAP_THRESHOLD_` / `MALLOC_TRIM_THRESHOLD_`,
/// which this sets from inside; those variables, when given, still win because glibc reads
/// them first — an explicit `mallopt` is only applied when they are absent).
/// Memory use stays bounded: the kept memory is reused by the next image.
fn keep_freed_images_mapped() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let user_set = |name: &str| std::env::var_os(name).is_some();
        // SAFETY: mallopt only changes allocator parameters; called before any thread exists.
        unsafe {
            if !user_set("MALLOC_MMAP_THRESHOLD_") {
                libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            }
            if !user_set("MALLOC_TRIM_THRESHOLD_") {
                libc::mallopt(libc::M_TRIM_THRESHOLD, 128 << 20);
            }
        }
    }
}

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so `println!` into a closed pipe (`gonio … --json | head`)
    // panics. Restore the default action: like every Unix filter, gonio then ends quietly
    // when its reader goes away. Nothing is lost by it: datasets are durable against any
    // kill (every stored measurement is fsynced before it is journalled), and progress
    // and logs go to stderr, so only a command's final report can meet a closed pipe.
    // SAFETY: called first thing in main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    keep_freed_images_mapped();
    let cli = gonio::cli::Cli::parse();
    gonio::cli::init_logging(cli.verbose, cli.quiet);
    match gonio::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
