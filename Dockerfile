# The virtualaxis emulator as a service: the runtime install (no test tools), run as a non-root user, with a
# healthcheck that asks the drive over CAN (`virtualaxis health`: the node answers SDO), not only whether the
# process lives. docker-compose.yml runs it on the host's SocketCAN vcan0 (profile vcan) or, for CI hosts
# without kernel CAN, on the host-local udp_multicast bus with fault injection (profile ci).
FROM python:3.11-slim
WORKDIR /opt/virtualaxis
COPY . .
RUN python3 -m pip install --no-cache-dir . && useradd --system --no-create-home --shell /usr/sbin/nologin virtualaxis
USER virtualaxis
ENV VIRTUALAXIS_CAN=socketcan:vcan0 VIRTUALAXIS_NODE_ID=1
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
  CMD virtualaxis health --can "$VIRTUALAXIS_CAN" --node-id "$VIRTUALAXIS_NODE_ID" --timeout 1
ENTRYPOINT ["virtualaxis"]
CMD ["serve", "--can", "socketcan:vcan0", "--node-id", "1", "--modbus", "127.0.0.1:5020", "--mqtt", "mqtt://127.0.0.1:1883"]
