import sys, threading, time
total = 0
started = False
for line in sys.stdin:
    total += int(line)
    print(total)
    if not started:
        threading.Thread(target=lambda: time.sleep(3600), daemon=True).start()
        started = True
