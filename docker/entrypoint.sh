#!/bin/sh
# Entry point of the sigmaslam images: before the command, check what a container's services need from the host and
# say what to do when it is missing, instead of a Permission denied or a missing file deep in a service.
#  - the output folders (SIGMASLAM_WRITABLE, default /outputs /recordings) must be writable by the uid the container
#    runs as: bind-mounted host folders that do not exist are made by the engine, owned by root;
#  - a mounted dataset (/data/dataset) must be an EuRoC ASL folder.
# The command's own exit code is kept; a failed check exits 78 (EX_CONFIG).
set -e

for dir in ${SIGMASLAM_WRITABLE-/outputs /recordings}; do
  if [ -d "$dir" ] && ! [ -w "$dir" ]; then
    echo "sigmaslam: $dir is not writable by uid $(id -u) (it belongs to uid $(stat -c %u "$dir")). On the host," \
         "create the output folders before 'up' and run the services as their owner, from the repository root:" \
         "mkdir -p out recordings; export SIGMASLAM_UID=\$(id -u) SIGMASLAM_GID=\$(id -g)" \
         "(as root: chown 10001:10001 out recordings). docs/deployment.md, 'Docker compose'." >&2
    exit 78
  fi
done

if [ -d /data/dataset ] && ! [ -d /data/dataset/mav0 ]; then
  echo "sigmaslam: /data/dataset (SIGMASLAM_DATASET on the host) is not an EuRoC ASL folder: it has no mav0/." \
       "Render the default replica first (.venv/bin/sigmaslam synth --default, from the repository root; an empty" \
       "folder there was made by the engine, owned by root: remove it first) or set SIGMASLAM_DATASET to a" \
       "sequence's folder. docs/deployment.md, 'Docker compose'." >&2
  exit 78
fi

exec "$@"
