# The virtualaxis emulator, installed the README's way (tests/test_services_packaging.py checks that the
# install steps below are the README's). Run with docker-compose.yml (host networking: SocketCAN vcan0 of the
# host, Modbus TCP on 127.0.0.1:5020, the mosquitto broker on 127.0.0.1:1883).
FROM python:3.11-slim
WORKDIR /opt/virtualaxis
COPY . .
RUN python3 -m pip install -e ".[dev]"
ENTRYPOINT ["virtualaxis"]
CMD ["serve", "--can", "socketcan:vcan0", "--node-id", "1", "--modbus", "127.0.0.1:5020", "--mqtt", "mqtt://127.0.0.1:1883"]
