"""What every stage stands on: the error type, progress callbacks, stage folders and manifests, the
stage contract, the runtime (device, threads, memory), interrupts, lazy package attributes and the
pictures stages share. Imports nothing else of cubecloud."""
